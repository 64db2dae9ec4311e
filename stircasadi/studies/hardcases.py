"""Scenes built to be hard for the estimator (the ``hard-cases`` study, ``scene = "hard:<name>"``).

When to use
-----------
As scene generators in a study spec; each factory returns ``(scene, grid, sensor)``. The study
asks of every one: all outputs finite, and no error beyond 4 sigma unless the estimate flags it
(verdict UNRELIABLE, an ambiguity naming the patch) or refuses with a clear error.

The cases (what makes each hard); the named scenes of ``stircasadi.testing.scenes`` (equal
path lengths of two hidden patches, a coplanar wall and collinear patches seen by an uncalibrated
camera, nine patches on three planes, a relay wall with two hidden squares) complete the
``hard-cases`` study as ``scene = "testing:<name>"``:

* ``equal_paths_visible``: three visible patches at the corners of an equilateral triangle
  centred on the camera axis: equal first onsets, equal second-bounce onsets.
* ``grazing``: a patch seen at 85 degrees from its normal (weak, stretched returns).
* ``albedo_0999``: three patches of albedo 0.999 (at the bound).
* ``dynamic_range``: a small hidden patch whose third bounce is about 1e-6 of the direct peak,
  with noise 30 times below that return.
* ``hidden_near_wall``: a hidden patch 1 mm behind the plane of a visible patch.
* ``screened_pair``: three patches, a screen blocks the second bounces of one pair (the small
  occluded scene of the ``effects`` study).
* ``missing_onsets`` is a study factor (``drop_direct``), ``SNR 0-5 dB`` is ``snr_db``: both act
  on any scene.

What it neglects
----------------
Each case is one fixed geometry (a seed moves only the noise); random scenes come from
``stircasadi.testing.scenes.generate`` (``scene = "testing:generate"``).
"""
from __future__ import annotations

import math

import numpy as np

from ..brdf import Lambertian
from ..errors import StudyError
from ..problems._common import paper_sensor, unit
from ..scene import Patch, Scene
from ..timegrid import TimeGrid

__all__ = ["HARD_CASES", "build_hard_case", "fit_grid"]


def fit_grid(scene: Scene, bin_width: float = 0.005, bounces: int = 3, margin: float = 0.3) -> TimeGrid:
    """A grid from 0 that holds every path of up to ``bounces`` bounces (plus ``margin`` m)."""
    z = scene.positions
    d = scene.distances
    longest = (np.max(np.linalg.norm(z - scene.source, axis=1)) + np.max(np.linalg.norm(z - scene.camera, axis=1))
               + max(bounces - 1, 0) * float(np.max(d)))
    return TimeGrid(start=0.0, bin_width=bin_width, n_bins=int(math.ceil((longest + margin) / bin_width)))


def _corner_visible():
    return [Patch((-0.20, 0.0, 1.20), (0.0, 0.0, -1.0), 0.01, Lambertian(0.8), name="V1"),
            Patch((0.45, 0.0, 0.90), tuple(unit((-1.0, 0.0, -0.3))), 0.01, Lambertian(0.6), name="V2")]


def equal_paths_visible(radius: float = 0.3, depth: float = 1.1, noise: float = 1e-5):
    patches = []
    for k in range(3):
        phi = 2 * math.pi * k / 3
        c = np.array([radius * math.cos(phi), radius * math.sin(phi), depth])
        inward = unit(-c * np.array([1.0, 1.0, 0.0]))
        patches.append(Patch(tuple(c), tuple(unit(0.6 * inward + np.array([0.0, 0.0, -1.0]))), 0.01,
                             Lambertian((0.7, 0.5, 0.9)[k]), name=f"P{k + 1}"))
    scene = Scene(patches, name="equal_paths_visible")
    return scene, fit_grid(scene, bounces=2), paper_sensor(noise)


def grazing(angle_deg: float = 85.0, noise: float = 1e-5):
    centres = [(0.30, 0.00, 1.00), (-0.30, 0.10, 1.10), (0.00, -0.30, 1.00)]
    normals = [unit((-0.50, 0.00, -1.0)), unit((0.40, 0.00, -1.0))]
    # the third patch: its normal at angle_deg from the direction to the camera, tilted toward
    # the other two so the second bounces stay
    to_cam = unit(-np.array(centres[2]))
    towards = unit(np.mean(centres[:2], axis=0) - np.array(centres[2]))
    perp = unit(towards - (towards @ to_cam) * to_cam)
    ang = math.radians(angle_deg)
    normals.append(unit(math.cos(ang) * to_cam + math.sin(ang) * perp))
    scene = Scene([Patch(c, tuple(n), 0.01, Lambertian(a), name=f"P{k + 1}")
                   for k, (c, n, a) in enumerate(zip(centres, normals, (0.7, 0.5, 0.9)))], name="grazing")
    return scene, fit_grid(scene, bounces=2), paper_sensor(noise)


def albedo_0999(noise: float = 1e-5):
    from ..problems import three_patch

    base = three_patch.build_scene()
    scene = Scene([Patch(p.centre, p.normal, p.area, Lambertian(0.999), name=p.name) for p in base.patches],
                  name="albedo_0999")
    return scene, three_patch.build_grid(), paper_sensor(noise)


def dynamic_range(hidden_area: float = 2.5e-5, noise: float = 3e-8):
    """One hidden patch of 5 mm x 5 mm: its third bounce is ~1e-6 of the direct peak."""
    v = _corner_visible()
    h = Patch((-0.45, 0.0, 0.60), tuple(unit((0.3, 0.0, 1.0))), hidden_area, Lambertian(0.7),
              hidden=True, name="H")
    scene = Scene(v + [h], name="dynamic_range")
    return scene, fit_grid(scene), paper_sensor(noise, calibrated_camera=True)


def hidden_near_wall(gap: float = 0.001, noise: float = 1e-6):
    """Visible V1 on the wall z = 1.2; the hidden patch sits 1 mm behind that plane, 8 cm
    beside V1, facing V2."""
    v = _corner_visible()
    c = np.array([-0.20 - 0.08, 0.0, 1.20 + gap])
    n = unit(np.array(v[1].centre) - c)
    h = Patch(tuple(c), tuple(n), 0.01, Lambertian(0.7), hidden=True, name="H")
    scene = Scene(v + [h], name="hidden_near_wall")
    return scene, fit_grid(scene), paper_sensor(noise, calibrated_camera=True)


def screened_pair(noise: float = 1e-5):
    """The paper's three patches with a screen between P1 and P2: their second bounces are
    blocked, the camera still sees all three (a small scene that calls for occlusion tests)."""
    import trimesh

    from ..problems import three_patch

    base = three_patch.build_scene()
    screen = trimesh.creation.box(extents=(0.02, 0.3, 0.3))
    screen.apply_translation(0.5 * (base.positions[0] + base.positions[1]))
    scene = Scene(base.patches, occluders=screen, name="screened_pair")
    return scene, three_patch.build_grid(), paper_sensor(noise)


HARD_CASES = {
    "equal_paths_visible": equal_paths_visible,
    "grazing": grazing,
    "albedo_0999": albedo_0999,
    "dynamic_range": dynamic_range,
    "hidden_near_wall": hidden_near_wall,
    "screened_pair": screened_pair,
}


def build_hard_case(name: str, **kwargs):
    """(scene, grid, sensor) of the named case."""
    if name not in HARD_CASES:
        raise StudyError(f"Unknown hard case {name!r}; the cases are {', '.join(HARD_CASES)}.")
    try:
        return HARD_CASES[name](**kwargs)
    except TypeError as exc:
        raise StudyError(f"Hard case {name!r} does not take {sorted(kwargs)}: {exc}") from exc
