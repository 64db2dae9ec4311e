"""Eight visible wall patches (two walls of a room corner) and one hidden
patch in front of them facing the walls, away from the camera; 160 bins, noise-free by default.
Hidden position and every albedo are solved jointly from the third bounces."""
from __future__ import annotations

from stircasadi.brdf import Lambertian
from stircasadi.scene import Patch, Scene
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid

from stircasadi.problems import lambertian_walls
from stircasadi.problems._common import gaussian_sensor, unit

NAME = "nine_patch_hidden"
DESCRIPTION = "Eight wall patches of a room corner and one hidden patch facing them, noise-free."


def build_scene() -> Scene:
    base = lambertian_walls.build_scene(8)
    hid = Patch((0.0, 0.25, 0.55), tuple(unit((0.0, -0.3, 0.954))), 0.02, Lambertian(0.6),
                hidden=True, name="H")
    return Scene(list(base.patches) + [hid], name=NAME)


def build_grid(n_bins: int = 160) -> TimeGrid:
    return TimeGrid(start=1.9, bin_width=3.0 / n_bins, n_bins=n_bins)


def build_sensor(noise_rel: float = 0.0) -> Sensor:
    return gaussian_sensor(noise_rel, fwhm_ps=60.0)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
