"""Scenes pinned for tests that were designed around a particular layout.

The problem scripts evolve (the default problems were redesigned so every quantity of the
default run is identifiable); these fixtures keep the exact layouts some tests were built for,
notably the original 3-patch scene in which two patches meet at exactly 90 degrees (no second
bounce between them: a missing distance).
"""
from __future__ import annotations

import numpy as np

from stircasadi.brdf import Lambertian
from stircasadi.scene import Patch, Scene


def _unit(v):
    v = np.asarray(v, float)
    return tuple(v / np.linalg.norm(v))


def three_patch_right_angle() -> Scene:
    """The first 3-patch layout: P2 and P3 face each other at exactly 90 degrees."""
    centres = [(0.30, 0.00, 1.00), (-0.30, 0.10, 1.10), (0.00, -0.30, 0.90)]
    normals = [(-0.30, 0.00, -1.0), (0.40, 0.00, -1.0), (0.00, 0.50, -1.0)]
    return Scene([Patch(c, _unit(n), 0.01, Lambertian(a), name=f"P{k + 1}")
                  for k, (c, n, a) in enumerate(zip(centres, normals, (0.7, 0.5, 0.9)))],
                 name="three_patch_right_angle")
