"""stircasadi: inverse transient light transport.

Recover patch positions (visible and hidden) and reflectance from space-time impulse responses
(STIRs), with the transient rendering equation written as a state-space model in CasADi and
solved with IPOPT. Conventions (units, axes, file format) are in DESIGN.md: lengths and times in
metres of optical path, time is the last axis, ``stir[i, j, k]`` = pulse at i, light from j, bin k.
"""
from __future__ import annotations

__version__ = "0.1.0"

from .capture import Capture
from .constants import C
from .errors import (CaptureError, SceneError, SolverError, StircasadiError, TimeGridError)
from .timegrid import TimeGrid

__all__ = ["__version__", "C", "Capture", "TimeGrid", "StircasadiError", "SceneError",
           "CaptureError", "TimeGridError", "SolverError"]
