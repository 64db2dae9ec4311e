"""The paper's 3-patch scene (Fig. 10): three visible Lambertian patches about 1 m from a
co-located source and camera. Geometry needs only second bounces (every pair is visible)."""
from __future__ import annotations


from stircasadi.brdf import Lambertian
from stircasadi.scene import Patch, Scene
from stircasadi.timegrid import TimeGrid

from stircasadi.problems._common import paper_sensor, unit

NAME = "three_patch"
DESCRIPTION = "Fig. 10: three visible Lambertian patches, every pair facing."
ALBEDOS = (0.7, 0.5, 0.9)
AREA = 0.01  # 10 cm x 10 cm


def build_scene() -> Scene:
    # every pair faces each other, so all three distances come from second bounces
    centres = [(0.30, 0.00, 1.00), (-0.30, 0.10, 1.10), (0.00, -0.30, 1.00)]
    normals = [(-0.50, 0.00, -1.0), (0.40, 0.00, -1.0), (0.00, 0.60, -1.0)]
    return Scene([Patch(c, tuple(unit(n)), AREA, Lambertian(a), name=f"P{k + 1}")
                  for k, (c, n, a) in enumerate(zip(centres, normals, ALBEDOS))], name=NAME)


def build_grid() -> TimeGrid:
    return TimeGrid(start=0.0, bin_width=0.005, n_bins=1024)


def build_sensor():
    return paper_sensor(noise_rel=1e-5)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
