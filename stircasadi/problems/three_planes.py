"""Three planar surfaces of 147 patches (Fig. 11): a back wall and two inclined side panels,
7 x 7 patches each, all visible. Geometry from second bounces; normals by fitting planes."""
from __future__ import annotations

import numpy as np

from stircasadi.scene import Scene
from stircasadi.timegrid import TimeGrid

from stircasadi.problems._common import paper_sensor, plane_patches, unit

NAME = "three_planes"
DESCRIPTION = "Fig. 11: 147 patches on three planes, all visible."
N_SIDE = 7
SPACING = 0.08
AREA = 0.004


def plane_specs():
    """(centre, normal, u_axis) of the three surfaces."""
    return [
        ((0.0, 0.0, 1.6), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0)),            # back wall
        ((-0.75, 0.0, 1.1), tuple(unit((0.8, 0.0, -0.6))), (0.0, 1.0, 0.0)),  # left panel
        ((0.75, 0.05, 1.1), tuple(unit((-0.8, 0.1, -0.6))), (0.0, 1.0, 0.0)),  # right panel
    ]


def albedos(n: int = 3 * N_SIDE * N_SIDE) -> np.ndarray:
    rng = np.random.default_rng(11)
    return rng.uniform(0.3, 0.9, n)


def build_scene(occluded: bool = False) -> Scene:
    alb = albedos()
    patches = []
    for s, (c, n, u) in enumerate(plane_specs()):
        k = len(patches)
        patches += plane_patches(c, n, u, N_SIDE, N_SIDE, SPACING, AREA,
                                 albedos=alb[k:k + N_SIDE * N_SIDE], prefix=f"S{s}_")
    occ = occluder() if occluded else None
    return Scene(patches, occluders=occ, name=NAME + ("_occluded" if occluded else ""))


def occluder():
    """A screen between the camera and the left panel (Fig. 13): blocks the camera's view of it."""
    import trimesh

    box = trimesh.creation.box(extents=(0.7, 1.0, 0.01))
    box.apply_translation((-0.42, 0.0, 0.45))
    return box


def plane_labels() -> np.ndarray:
    return np.repeat(np.arange(3), N_SIDE * N_SIDE)


def build_grid() -> TimeGrid:
    return TimeGrid(start=0.0, bin_width=0.01, n_bins=1024)


def build_sensor():
    return paper_sensor(noise_rel=1e-6)  # second bounces are ~1e-4 of the peak: keep them visible


def truth(occluded: bool = False) -> dict:
    t = build_scene(occluded).truth_dict()
    t["plane"] = plane_labels()
    return t


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
