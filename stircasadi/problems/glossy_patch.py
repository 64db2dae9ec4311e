"""Twin-experiment scene for Phong parameters: five visible patches around one glossy (modified
Phong) patch placed so that light from its neighbours reflects near its mirror direction."""
from __future__ import annotations

from stircasadi.brdf import Lambertian, Phong
from stircasadi.scene import Patch, Scene
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid

from stircasadi.problems._common import gaussian_sensor, unit

NAME = "glossy_patch"
DESCRIPTION = "One glossy (modified Phong) patch among four Lambertian ones; a reflectance twin with known geometry."
#: ``stircasadi run`` exercises the reflectance stage only: the problem gives the visible geometry
ESTIMATE = {"stage": "reflectance", "brdf": "phong"}
GLOSSY = Phong(albedo=0.3, specular=0.5, exponent=8.0)


def build_scene() -> Scene:
    P = [Patch((0.0, -0.25, 1.2), tuple(unit((0.0, 1.0, -0.6))), 0.006, GLOSSY, name="G"),
         Patch((-0.35, 0.1, 1.1), tuple(unit((0.6, -0.3, -1.0))), 0.006, Lambertian(0.7), name="L1"),
         Patch((0.35, 0.12, 1.1), tuple(unit((-0.6, -0.3, -1.0))), 0.006, Lambertian(0.5), name="L2"),
         Patch((0.0, 0.3, 1.3), tuple(unit((0.0, -0.6, -1.0))), 0.006, Lambertian(0.8), name="L3"),
         Patch((-0.05, 0.0, 1.5), tuple(unit((0.0, 0.1, -1.0))), 0.006, Lambertian(0.6), name="L4")]
    return Scene(P, name=NAME)


def build_grid() -> TimeGrid:
    return TimeGrid(start=1.8, bin_width=0.004, n_bins=500)


def build_sensor(noise_rel: float = 1e-3) -> Sensor:
    return gaussian_sensor(noise_rel, fwhm_ps=60.0)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
