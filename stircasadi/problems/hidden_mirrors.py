"""The paper's third experiment: two hidden mirrors facing a diffuse wall. A mirror shows up
only for wall pairs (i, j) whose specular path i -> mirror -> j exists, at the path length of
the mirror image; the mirrors' positions and orientations follow from those third onsets."""
from __future__ import annotations


from stircasadi.brdf import Lambertian, Mirror
from stircasadi.scene import Patch, Scene
from stircasadi.timegrid import TimeGrid

from stircasadi.problems._common import paper_sensor, plane_patches, unit

NAME = "hidden_mirrors"
DESCRIPTION = "Two hidden mirrors facing a 9 x 9 diffuse wall (image-source transfer)."


def build_scene() -> Scene:
    wall = plane_patches((0.0, 0.0, 1.5), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 9, 9, 0.1, 0.0064,
                         brdf=Lambertian(0.8), prefix="W")
    mirrors = [Patch((0.15, 0.1, 0.9), tuple(unit((0.0, 0.0, 1.0))), 0.02, Mirror(0.95), name="M1"),
               Patch((-0.2, -0.15, 1.0), tuple(unit((0.25, 0.1, 1.0))), 0.02, Mirror(0.95), name="M2")]
    return Scene(wall + mirrors, name=NAME)


def build_grid() -> TimeGrid:
    return TimeGrid(start=0.0, bin_width=0.005, n_bins=1536)


def build_sensor():
    return paper_sensor(noise_rel=1e-6)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
