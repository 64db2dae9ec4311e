"""The CPUs this process may use (its affinity where the platform reports one, else the count).

When to use: every default that sizes a pool of threads or worker processes
(``nlos.surface.SurfaceSettings.n_threads``, ``studies.runner.default_workers``)."""
from __future__ import annotations

import os

__all__ = ["usable_cpus"]


def usable_cpus() -> int:
    """CPUs this process may run on (>= 1)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):     # not on Linux
        return max(1, os.cpu_count() or 1)
