"""Twin-experiment scene for reflectance: N visible Lambertian patches on the two walls of a room
corner (they see each other, so second bounces exist), random albedos in [0.3, 0.9].
``build_scene(n_patches)`` (even n, 10 by default) and ``build_grid(n_bins)`` scale it for the
reflectance benchmarks (10-100 patches, 512-4096 bins); 1 % Gaussian noise by default."""
from __future__ import annotations

import numpy as np

from stircasadi.scene import Scene
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid

from stircasadi.problems._common import gaussian_sensor, plane_patches, unit

NAME = "lambertian_walls"
DESCRIPTION = "N Lambertian patches on the two walls of a room corner; a reflectance twin with known geometry."
#: ``stircasadi run`` exercises the reflectance stage only: the problem gives the visible geometry
ESTIMATE = {"stage": "reflectance"}
SPAN = 0.6      # metres covered by each wall's patches
AREA = 0.004


def albedos(n: int) -> np.ndarray:
    return np.random.default_rng(7).uniform(0.3, 0.9, n)


def _grid_shape(n_half: int) -> tuple[int, int]:
    rows = max(1, int(np.floor(np.sqrt(n_half / 2.0))))
    while n_half % rows:
        rows -= 1
    return n_half // rows, rows


def build_scene(n_patches: int = 10) -> Scene:
    if n_patches < 2 or n_patches % 2:
        raise ValueError(f"n_patches must be an even number >= 2 (two walls); got {n_patches}.")
    half = n_patches // 2
    nu, nv = _grid_shape(half)
    spacing = SPAN / max(nu, 1)
    alb = albedos(n_patches)
    specs = [((-0.35, 0.0, 1.2), unit((0.7, 0.0, -0.7)), (0.0, 0.0, 1.0)),
             ((0.35, 0.0, 1.2), unit((-0.7, 0.05, -0.7)), (0.0, 0.0, 1.0))]
    patches = []
    for s, (c, n, u) in enumerate(specs):
        u = np.cross(n, (0.0, 1.0, 0.0))
        patches += plane_patches(c, n, u, nu, nv, spacing, min(AREA, 0.5 * spacing ** 2),
                                 albedos=alb[len(patches):len(patches) + half], prefix=f"W{s}_")
    return Scene(patches, name=f"{NAME}_{n_patches}")


def build_grid(n_bins: int = 1024) -> TimeGrid:
    return TimeGrid(start=1.5, bin_width=3.0 / n_bins, n_bins=n_bins)


def build_sensor(noise_rel: float = 1e-2) -> Sensor:
    return gaussian_sensor(noise_rel, fwhm_ps=60.0)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
