"""Fig. 13: the three planes of Fig. 11 with the second (left) surface occluded from the camera
by a screen. Its 49 patches are hidden: found from third bounces off the two visible surfaces."""
from __future__ import annotations

from stircasadi.scene import Scene

from stircasadi.problems import three_planes as _base

NAME = "three_planes_occluded"
DESCRIPTION = "Fig. 13: the three planes with the left one hidden behind a screen."
build_grid = _base.build_grid
build_sensor = _base.build_sensor
plane_labels = _base.plane_labels
#: what ``stircasadi run`` passes the estimator: the joint route adds the 49-patch hidden panel one
#: point patch at a time (3-12 min per candidate on 2 cores), so ``run`` stops it after 15 min and
#: reports the visible patches' fit, flagged UNRELIABLE by the ``time-limit`` check; the panel
#: is a surface (``stircasadi.nlos`` surface route)
ESTIMATE = {"time_limit": 900.0}


def build_scene() -> Scene:
    return _base.build_scene(occluded=True)


def truth() -> dict:
    return _base.truth(occluded=True)


if __name__ == "__main__":
    import sys

    from stircasadi.problem import problem_main
    problem_main(sys.modules[__name__])
