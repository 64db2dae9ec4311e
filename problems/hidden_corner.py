"""The paper's 4-patch corner (Fig. 12): two visible patches on a wall and two hidden patches
that face the wall, away from the camera. Hidden geometry comes from third bounces
(pulse at a visible patch -> hidden patch -> visible patch -> camera). The default problem."""
from __future__ import annotations

from stircasadi.brdf import Lambertian
from stircasadi.scene import Patch, Scene
from stircasadi.timegrid import TimeGrid

from ._common import paper_sensor, standard_main, unit

NAME = "hidden_corner"
ALBEDOS = (0.8, 0.6, 0.7, 0.5)


def build_scene() -> Scene:
    wall = [Patch((-0.25, 0.0, 1.2), (0.0, 0.0, -1.0), 0.01, Lambertian(ALBEDOS[0]), name="V1"),
            Patch((0.25, 0.05, 1.2), (0.0, 0.0, -1.0), 0.01, Lambertian(ALBEDOS[1]), name="V2")]
    hidden = [Patch((0.45, -0.15, 0.75), tuple(unit((-0.4, 0.1, 1.0))), 0.04, Lambertian(ALBEDOS[2]), name="H1"),
              Patch((-0.40, 0.20, 0.70), tuple(unit((0.35, -0.2, 1.0))), 0.04, Lambertian(ALBEDOS[3]), name="H2")]
    return Scene(wall + hidden, name=NAME)


def build_grid() -> TimeGrid:
    return TimeGrid(start=0.0, bin_width=0.005, n_bins=1024)


def build_sensor():
    return paper_sensor(noise_rel=1e-7)


def truth() -> dict:
    return build_scene().truth_dict()


def main() -> None:
    import sys
    standard_main(sys.modules[__name__])


if __name__ == "__main__":
    main()
