"""Inverse geometry (Algorithm 1, step 1): from a Capture alone, where every patch is.

Pipeline (``estimate_geometry``)::

    traces --onsets.py--> O1, O2 (+ sigma), third onsets
           --distances.py--> D, eps  (weighted least squares on T2 d = O)
           --embedding.py--> positions (classical MDS, source at origin; IPOPT inside eps)
           --normals.py--> normals, plane groups
           --hidden.py--> hidden distances (T3) and positions (trilateration), ambiguities
    relay / confocal captures --relay.py--> hidden surfaces from sphere / ellipsoid constraints

The result is a ``GeometryEstimate`` (``result.py``); ``stircasadi.report`` compares it with a truth.
"""
from __future__ import annotations

from .result import GeometryEstimate, StageStats

__all__ = ["GeometryEstimate", "StageStats", "estimate_geometry"]


def estimate_geometry(capture, hidden=None, settings=None):
    """Run the geometry stage on ``capture``; see ``stircasadi.geometry.estimate``."""
    from .estimate import estimate_geometry as _impl

    return _impl(capture, hidden=hidden, settings=settings)
