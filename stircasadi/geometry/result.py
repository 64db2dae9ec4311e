"""``GeometryEstimate``: what the geometry stage hands to the reflectance stage and writes to JSON.

Frames: when the capture gives the visible points (``observed_xyz``, a relay wall, a calibrated
camera) positions are in the capture's frame (``frame = "capture"``); otherwise the source sits
at the origin and the frame is fixed only up to a rotation/reflection about it (``frame =
"source-origin"``; compare by Procrustes, see ``stircasadi.report.alignment``).

Distances: ``distances[a, b]`` is the estimated distance between patches ``ids[a]`` and
``ids[b]`` (NaN where nothing measured it) and ``eps[a, b]`` its error bound at confidence
``eps_level`` (see ``distances.py`` for how it is derived; inf where unknown).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

from ..report import jsonable

import numpy as np

__all__ = ["GeometryEstimate", "StageStats"]


def _arr(x, shape_tail=None, fill=np.nan) -> np.ndarray:
    a = np.array([fill if v is None else v for v in x] if isinstance(x, list) and x and not
                 isinstance(x[0], list) else x, dtype=float)
    return a


@dataclass
class StageStats:
    """One stage of the geometry pipeline: name, solver status, iterations, wall time."""

    name: str
    status: str = "ok"
    iterations: int = 0
    wall_time_s: float = 0.0
    success: bool = True
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {"status": self.status, "success": self.success, "iterations": int(self.iterations),
             "wall_time_s": float(self.wall_time_s)}
        d.update(self.extra)
        return jsonable(d)


@dataclass
class GeometryEstimate:
    """Positions, normals, distances with bounds, and hidden patches from a Capture.

    Attributes
    ----------
    ids : (M,) int -- visible patches keep the capture's observed ids; hidden patches get ids
        no visible patch uses (max id + 1, ...).
    positions : (M, 3) metres.
    normals : (M, 3) unit normals, NaN where not estimated.
    visible : (M,) bool.
    distances : (M, M) metres, NaN where unknown.
    eps : (M, M) bound on |distances - truth| at confidence ``eps_level``; inf where unknown.
    position_std : (M, 3) one-sigma position uncertainty (NaN where unknown).
    hidden_distance_bounds : one dict per hidden patch: ``id``, ``visible_ids``, ``distances``,
        ``eps`` (the hidden-to-visible distances from third onsets, before trilateration).
    source_xyz, camera_xyz : (3,) in the estimate's frame.
    frame : ``"capture"`` or ``"source-origin"``.
    plane_labels : (M,) int plane group (-1 = none) from the normals stage, or None.
    onsets : dict of the onset arrays used (``O1``, ``O1_std``, ``O2``, ``O2_std``, ...).
    stats : stage name -> ``StageStats``.
    ambiguities : list of dicts ``{"kind", "patches", "message", ...}`` -- what the data could
        not decide (mirror solutions, merged onsets, underdetermined hidden patches...).
    eps_level : the two-sided confidence of ``eps``.
    """

    ids: np.ndarray
    positions: np.ndarray
    visible: np.ndarray
    normals: np.ndarray | None = None
    distances: np.ndarray | None = None
    eps: np.ndarray | None = None
    position_std: np.ndarray | None = None
    hidden_distance_bounds: list = field(default_factory=list)
    source_xyz: np.ndarray | None = None
    camera_xyz: np.ndarray | None = None
    frame: str = "source-origin"
    plane_labels: np.ndarray | None = None
    onsets: dict = field(default_factory=dict)
    stats: dict = field(default_factory=dict)
    ambiguities: list = field(default_factory=list)
    eps_level: float = 0.99
    extras: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, dtype=np.int64)
        m = len(self.ids)
        self.positions = np.asarray(self.positions, dtype=float).reshape(m, 3)
        self.visible = np.asarray(self.visible, dtype=bool).reshape(m)
        if self.normals is None:
            self.normals = np.full((m, 3), np.nan)
        self.normals = np.asarray(self.normals, dtype=float).reshape(m, 3)
        if self.distances is None:
            self.distances = np.full((m, m), np.nan)
        if self.eps is None:
            self.eps = np.full((m, m), np.inf)
        if self.position_std is None:
            self.position_std = np.full((m, 3), np.nan)
        self.position_std = np.asarray(self.position_std, dtype=float).reshape(m, 3)

    # ------------------------------------------------------------------ views
    @property
    def n_patches(self) -> int:
        return len(self.ids)

    @property
    def hidden_ids(self) -> np.ndarray:
        return self.ids[~self.visible]

    def index_of(self, patch_id: int) -> int:
        hit = np.flatnonzero(self.ids == patch_id)
        if hit.size == 0:
            raise KeyError(f"patch id {patch_id} not in this estimate (ids {self.ids.tolist()[:20]})")
        return int(hit[0])

    @property
    def success(self) -> bool:
        return all(getattr(s, "success", True) for s in self.stats.values())

    # ------------------------------------------------------------------ JSON
    def to_json_dict(self) -> dict:
        """The ``estimate.json`` structure of DESIGN.md section 5 (geometry part)."""
        patches = []
        for a in range(self.n_patches):
            patches.append({"id": int(self.ids[a]), "visible": bool(self.visible[a]),
                            "position": self.positions[a], "normal": self.normals[a],
                            "position_std": self.position_std[a],
                            "plane": None if self.plane_labels is None else int(self.plane_labels[a])})
        out = {
            "format": "stircasadi.estimate", "version": 1, "frame": self.frame,
            "source_xyz": self.source_xyz, "camera_xyz": self.camera_xyz,
            "patches": patches,
            "distances": {"ids": self.ids, "matrix": self.distances, "eps": self.eps,
                          "eps_level": self.eps_level},
            "hidden_distance_bounds": self.hidden_distance_bounds,
            "stages": {k: (v.to_dict() if isinstance(v, StageStats) else v) for k, v in self.stats.items()},
            "ambiguities": self.ambiguities,
            "success": self.success,
        }
        return jsonable(out)

    def to_json(self, path=None, indent: int = 1) -> str:
        text = json.dumps(self.to_json_dict(), indent=indent)
        if path is not None:
            with open(path, "w") as f:
                f.write(text)
        return text

    @classmethod
    def from_json_dict(cls, d: dict) -> "GeometryEstimate":
        """Inverse of ``to_json_dict`` (None -> NaN; unknown eps -> inf)."""
        def f(v):
            return np.nan if v is None else v

        pats = d["patches"]
        ids = [p["id"] for p in pats]
        pos = [[f(v) for v in p["position"]] for p in pats]
        nor = [[f(v) for v in (p.get("normal") or [None] * 3)] for p in pats]
        std = [[f(v) for v in (p.get("position_std") or [None] * 3)] for p in pats]
        dist = d.get("distances", {})
        D = np.array([[f(v) for v in row] for row in dist.get("matrix", [])], dtype=float) \
            if dist.get("matrix") else None
        E = np.array([[np.inf if v is None else v for v in row] for row in dist.get("eps", [])],
                     dtype=float) if dist.get("eps") else None
        stats = {k: StageStats(k, v.get("status", "ok"), v.get("iterations", 0),
                               v.get("wall_time_s", 0.0), v.get("success", True))
                 for k, v in d.get("stages", {}).items()}
        planes = [p.get("plane") for p in pats]
        return cls(ids=ids, positions=pos, visible=[p["visible"] for p in pats], normals=nor,
                   distances=D, eps=E, position_std=std,
                   hidden_distance_bounds=d.get("hidden_distance_bounds", []),
                   source_xyz=None if d.get("source_xyz") is None else np.array(d["source_xyz"], float),
                   camera_xyz=None if d.get("camera_xyz") is None else np.array(d["camera_xyz"], float),
                   frame=d.get("frame", "source-origin"),
                   plane_labels=None if any(p is None for p in planes) else np.array(planes),
                   stats=stats, ambiguities=d.get("ambiguities", []),
                   eps_level=dist.get("eps_level", 0.99))
