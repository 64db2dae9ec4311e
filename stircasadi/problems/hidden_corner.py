"""The paper's 4-patch corner (Fig. 12), the default problem: two visible patches on the two
walls of a corner (they see each other, so their distance comes from second bounces) and two
hidden patches that face the walls, away from the camera. Everything lies in the plane y = 0
(a "flatland" corner, as in the figure): with two visible patches, third-bounce distances place
a hidden patch on a circle about the line through them, and the plane picks the point (the
geometry stage reports the ambiguity and keeps the solution on the camera's side).

The camera is calibrated (pixel rays and the visible surfaces' normals are known), so the joint
NLP can identify the hidden patches' albedos and orientations from third-bounce amplitudes.
"""
from __future__ import annotations

from stircasadi.brdf import Lambertian
from stircasadi.scene import Patch, Scene
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid

from stircasadi.problems._common import paper_sensor, unit

NAME = "hidden_corner"
DESCRIPTION = "Fig. 12: a flatland corner, 2 visible and 2 hidden patches, calibrated camera (the default)."
N_HIDDEN = 2
NOISE_REL = 1e-6
#: what the experimenter knows and declares (written to the capture's priors/ group)
PRIORS = {"flatland": True}


def build_scene() -> Scene:
    return Scene([
        Patch((-0.20, 0.0, 1.20), (0.0, 0.0, -1.0), 0.01, Lambertian(0.8), name="V1"),
        Patch((0.45, 0.0, 0.90), unit((-1.0, 0.0, -0.3)), 0.01, Lambertian(0.6), name="V2"),
        Patch((-0.45, 0.0, 0.60), unit((0.3, 0.0, 1.0)), 0.04, Lambertian(0.7), name="H1"),
        Patch((0.10, 0.0, 0.55), unit((-0.2, 0.0, 1.0)), 0.04, Lambertian(0.5), name="H2"),
    ], name=NAME)


def build_grid() -> TimeGrid:
    return TimeGrid(start=0.0, bin_width=0.005, n_bins=1024)


def build_sensor() -> Sensor:
    """210 ps FWHM Gaussian response, Gaussian noise at 1e-6 of the peak, calibrated camera."""
    return paper_sensor(NOISE_REL, calibrated_camera=True)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
