"""Inverse geometry (Algorithm 1, step 1): from a Capture alone, where every patch is.

Pipeline (``estimate_geometry``)::

    traces --onsets.py--> O1, O2 (+ sigma), third onsets
           --distances.py--> D, eps  (weighted least squares on T2 d = O)
           --embedding.py--> positions (classical MDS, source at origin; IPOPT inside eps)
           --normals.py--> normals, plane groups
           --hidden.py--> hidden distances (T3) and positions (trilateration), ambiguities
    relay / confocal captures --relay.py--> hidden surfaces from sphere / ellipsoid constraints

The result is a ``GeometryEstimate`` (``result.py``); ``report_table`` prints it against a truth.
"""
from __future__ import annotations

from .result import GeometryEstimate, StageStats

__all__ = ["GeometryEstimate", "StageStats", "estimate_geometry", "report_table"]


def estimate_geometry(capture, hidden=None, settings=None):
    """Run the geometry stage on ``capture``; see ``stircasadi.geometry.estimate``."""
    from .estimate import estimate_geometry as _impl

    return _impl(capture, hidden=hidden, settings=settings)


def report_table(estimate, truth) -> str:
    """Estimated vs true positions (Procrustes-aligned when frames differ); see ``report``."""
    from .report import report_table as _impl

    return _impl(estimate, truth)
