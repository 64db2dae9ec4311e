"""A wall-clock allowance for one estimate: solves stop at it, the search starts nothing past it.

When to use: ``EstimateSettings.time_limit`` (seconds; ``stircasadi estimate --time-limit``) makes
``fit_joint`` create one ``Budget`` and hand it to every NLP it builds (``JointNLP.budget``).
IPOPT gets the time left as ``max_wall_time``, the sparse Gauss-Newton solver checks it every
iteration, and the hidden-patch search, the extent screening and the final joint fit are not
started once it has run out. A fit that the limit cut short is never reported as a result: the
estimate is then the last fit that converged with every unknown free (the visible patches'),
flagged by the ``time-limit`` check (``success`` false), or, when no fit converged in time, a
``SolverError`` that says which stage the limit stopped.
"""
from __future__ import annotations

import math
import time

__all__ = ["Budget", "WALL_TIME_STATUS"]

#: the status a solve ends with when the budget stopped it (IPOPT's own name)
WALL_TIME_STATUS = "Maximum_WallTime_Exceeded"


class Budget:
    """``seconds`` of wall time from now (None: unlimited)."""

    def __init__(self, seconds: float | None = None, start: float | None = None):
        if seconds is not None and not (math.isfinite(float(seconds)) and float(seconds) > 0):
            raise ValueError(f"a time limit must be a positive number of seconds; got {seconds!r}")
        self.limit = None if seconds is None else float(seconds)
        self.start = time.perf_counter() if start is None else float(start)
        self.stopped: list[str] = []   # the stages the limit stopped or skipped, in order

    @property
    def limited(self) -> bool:
        return self.limit is not None

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def remaining(self) -> float:
        return math.inf if self.limit is None else self.limit - self.elapsed()

    def expired(self) -> bool:
        return self.remaining() <= 0.0

    def ipopt_options(self) -> dict:
        """IPOPT's ``max_wall_time`` for the time left (at least 1 s, so a solve can report)."""
        return {} if self.limit is None else {"max_wall_time": max(self.remaining(), 1.0)}

    def stop(self, stage: str) -> None:
        """Record that the limit stopped (or skipped) ``stage``."""
        if stage not in self.stopped:
            self.stopped.append(stage)

    def summary(self) -> str:
        """What the limit cut, in the words the fit's note and the ``time-limit`` check share."""
        return (f"the time limit of {self.limit:g} s ran out in: {', '.join(self.stopped)}; the "
                "estimate is the last fit that converged with every unknown free")

    def to_dict(self) -> dict:
        return {"limit_s": self.limit, "elapsed_s": self.elapsed(), "stopped": list(self.stopped)}
