"""``Capture``: the one measured-or-simulated data type, and its HDF5 file (DESIGN.md section 4).

A Capture flows from the simulator (``Sensor.capture``) and from the instruments and importers
(``stircasadi.acquisition``) into the estimators, so a twin experiment and a real measurement
take the same road.

File layout (version 1), written and read here::

    /                      attrs: format="stircasadi.capture", version=1, start_m, bin_width_m,
                                  legs_included (bool)
    /stir                  float64 (n_illuminated, n_observed, n_bins)        -- full STIR, or
    /traces, /pairs        float64 (n_pairs, n_bins), int (n_pairs, 2)        -- paired/confocal
    /source_xyz (3,)  /camera_xyz (3,)  /illuminated_xyz (n_ill, 3)  /observed_xyz (n_obs, 3)
    /illuminated_ids  /observed_ids (int)   /irf (1-D, same bin width, peak at centre)
    /noise                 attrs: model, sigma / counts / background
    /truth/                positions, normals, areas, albedo, visible [, specular, exponent]; attr brdf
    /provenance/           attrs: producer, date, instrument, ...
    anything else          kept verbatim in ``Capture.extras`` and written back

Design note: DESIGN.md lists Capture under ``sensor.py``; it lives in its own module so that the
acquisition side can import it without the simulator, and ``stircasadi.sensor`` re-exports it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import CaptureError
from .io import atomic_path, check_output
from .timegrid import TimeGrid

FORMAT = "stircasadi.capture"
VERSION = 1
_KNOWN_DATASETS = ("stir", "traces", "pairs", "source_xyz", "camera_xyz", "illuminated_xyz",
                   "observed_xyz", "illuminated_ids", "observed_ids", "irf")
_KNOWN_GROUPS = ("noise", "truth", "provenance")
_TRUTH_BRDFS = ("lambertian", "phong", "mirror", "mixed")


def _as_float_array(name: str, value: Any, ndim: int | None = None,
                    shape: tuple | None = None) -> np.ndarray:
    raw = value if isinstance(value, np.ndarray) else None
    if raw is None:
        try:
            raw = np.asarray(value)
        except (TypeError, ValueError) as exc:
            raise CaptureError(f"Capture field '{name}' must be numeric; got {type(value).__name__}.") from exc
    kind = raw.dtype.kind
    if kind in "bc" or kind not in "iuf":
        what = {"b": "booleans", "c": "complex numbers"}.get(kind, f"dtype {raw.dtype}")
        raise CaptureError(f"Capture field '{name}' must hold real numbers (float64); got {what}. "
                           "Convert it explicitly (e.g. take .real or .astype(float)) before building "
                           "the Capture.")
    arr = raw.astype(np.float64, copy=False)
    if ndim is not None and arr.ndim != ndim:
        raise CaptureError(f"Capture field '{name}' must have {ndim} dimensions; got shape {arr.shape}.")
    if shape is not None:
        for want, got in zip(shape, arr.shape):
            if want is not None and want != got:
                raise CaptureError(f"Capture field '{name}' must have shape {shape} "
                                   f"(None = any); got {arr.shape}.")
    if not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise CaptureError(f"Capture field '{name}' holds {bad} NaN/inf value(s); all values must "
                           "be finite. Mark missing traces by leaving them out (paired form) instead.")
    return arr


def _as_int_array(name: str, value: Any) -> np.ndarray:
    arr = np.asarray(value)
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        if np.issubdtype(arr.dtype, np.floating) and np.all(np.isfinite(arr)) and np.all(arr == np.round(arr)):
            arr = arr.astype(np.int64)
        else:
            raise CaptureError(f"Capture field '{name}' must hold integers (patch ids); got dtype {arr.dtype}.")
    arr = arr.astype(np.int64)
    if arr.size and arr.min() < 0:
        raise CaptureError(f"Capture field '{name}' holds negative patch id(s) "
                           f"{sorted(set(arr[arr < 0].tolist()))[:10]}; patch ids are integers >= 0.")
    return arr


def _as_bool(name: str, value: Any) -> bool:
    """A flag stored as a boolean (or 0/1); the string 'False' is refused, never read as True."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)) and value in (0, 1):
        return bool(value)
    raise CaptureError(f"Capture field '{name}' must be a boolean (True/False); got "
                       f"{type(value).__name__} {value!r}. Store it as a boolean (HDF5: a bool "
                       "attribute), not as text.")


#: noise attributes that are numbers, and the smallest value each may take
_NOISE_NUMBERS = {"sigma": 0.0, "background": 0.0, "scale": 0.0, "counts": 0.0}


def _validate_noise(noise: Any) -> dict:
    if not isinstance(noise, dict):
        raise CaptureError(f"Capture field 'noise' must be a dict of attributes; got {type(noise).__name__}.")
    for key, low in _NOISE_NUMBERS.items():
        if key not in noise or noise[key] is None:
            continue
        v = noise[key]
        if isinstance(v, np.generic):
            v = v.item()
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < low:
            raise CaptureError(f"Capture noise attribute '{key}' must be a finite number >= {low:g} "
                               f"(in the STIR's units); got {type(v).__name__} {v!r}. Store it as a "
                               "number, e.g. noise={'model': 'gaussian', 'sigma': 0.01}.")
        noise[key] = float(v)
    if "shots" in noise and noise["shots"] is not None:
        v = noise["shots"]
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
            raise CaptureError(f"Capture noise attribute 'shots' must be an integer >= 1; got {v!r}.")
    if "model" in noise and not isinstance(noise["model"], str):
        raise CaptureError(f"Capture noise attribute 'model' must be text ('gaussian', 'poisson', "
                           f"'none'); got {noise['model']!r}.")
    return noise


@dataclass
class Capture:
    """A time-resolved measurement: the full STIR or a set of (illuminated, observed) traces.

    Exactly one of ``stir`` or (``traces``, ``pairs``) is given. Arrays are float64, time last,
    in metres of optical path on ``grid``. ``legs_included`` says whether times include the
    source-to-first-patch and last-patch-to-camera legs (rectified relay-wall data: False).
    """

    grid: TimeGrid
    stir: np.ndarray | None = None
    traces: np.ndarray | None = None
    pairs: np.ndarray | None = None
    legs_included: bool = True
    source_xyz: np.ndarray | None = None
    camera_xyz: np.ndarray | None = None
    illuminated_xyz: np.ndarray | None = None
    observed_xyz: np.ndarray | None = None
    illuminated_ids: np.ndarray | None = None
    observed_ids: np.ndarray | None = None
    irf: np.ndarray | None = None
    noise: dict = field(default_factory=dict)
    truth: dict | None = None
    provenance: dict = field(default_factory=dict)
    extras: dict = field(default_factory=dict)
    #: effects applied by the simulator and other in-memory notes (not a file field)
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ validation
    def validate(self) -> "Capture":
        """Check shapes, finiteness and consistency; raise ``CaptureError`` naming the field."""
        if not isinstance(self.grid, TimeGrid):
            raise CaptureError(f"Capture field 'grid' must be a TimeGrid; got {type(self.grid).__name__}.")
        nb = self.grid.n_bins
        if (self.stir is None) == (self.traces is None):
            raise CaptureError("A Capture holds exactly one of 'stir' (n_illuminated, n_observed, "
                               "n_bins) or 'traces' (n_pairs, n_bins) with 'pairs'; got "
                               f"{'both' if self.stir is not None else 'neither'}.")
        if self.stir is not None:
            self.stir = _as_float_array("stir", self.stir, ndim=3)
            if self.stir.shape[2] != nb:
                raise CaptureError(f"Capture field 'stir' has {self.stir.shape[2]} time bins but the "
                                   f"grid has n_bins={nb}; time is the last axis.")
            if self.pairs is not None:
                raise CaptureError("Capture field 'pairs' is only allowed with 'traces', not with 'stir'.")
            n_ill, n_obs = self.stir.shape[:2]
        else:
            self.traces = _as_float_array("traces", self.traces, ndim=2)
            if self.traces.shape[1] != nb:
                raise CaptureError(f"Capture field 'traces' has {self.traces.shape[1]} time bins but "
                                   f"the grid has n_bins={nb}; time is the last axis.")
            if self.pairs is None:
                raise CaptureError("Capture field 'pairs' (n_pairs, 2) is required with 'traces'.")
            self.pairs = _as_int_array("pairs", self.pairs)
            if self.pairs.ndim != 2 or self.pairs.shape != (self.traces.shape[0], 2):
                raise CaptureError(f"Capture field 'pairs' must have shape ({self.traces.shape[0]}, 2) "
                                   f"to match 'traces'; got {self.pairs.shape}.")
            uniq, counts = np.unique(self.pairs, axis=0, return_counts=True)
            if uniq.shape[0] != self.pairs.shape[0]:
                dup = uniq[counts > 1][:5].tolist()
                raise CaptureError(f"Capture field 'pairs' names the pair(s) {dup} (illuminated, "
                                   "observed) more than once; each pair may have one trace. Sum or "
                                   "average the repeated traces first.")
            n_ill = n_obs = None
        self.legs_included = _as_bool("legs_included", self.legs_included)
        for name in ("source_xyz", "camera_xyz"):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, _as_float_array(name, v, ndim=1, shape=(3,)))
        for name, n in (("illuminated_xyz", n_ill), ("observed_xyz", n_obs)):
            v = getattr(self, name)
            if v is not None:
                setattr(self, name, _as_float_array(name, v, ndim=2, shape=(n, 3)))
        for name, n in (("illuminated_ids", n_ill), ("observed_ids", n_obs)):
            v = getattr(self, name)
            if v is not None:
                arr = _as_int_array(name, v)
                if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
                    raise CaptureError(f"Capture field '{name}' must be 1-D of length {n}; got {arr.shape}.")
                if len(np.unique(arr)) != len(arr):
                    raise CaptureError(f"Capture field '{name}' holds duplicate ids: {arr.tolist()[:20]}.")
                setattr(self, name, arr)
        if self.irf is not None:
            self.irf = _as_float_array("irf", self.irf, ndim=1)
            if self.irf.size < 1 or self.irf.sum() <= 0:
                raise CaptureError("Capture field 'irf' must be a non-empty 1-D array with a positive sum.")
        if self.truth is not None:
            self._validate_truth()
        self.noise = _validate_noise(self.noise)
        if not isinstance(self.provenance, dict):
            raise CaptureError("Capture field 'provenance' must be a dict of attributes.")
        return self

    def _validate_truth(self) -> None:
        t = self.truth
        if not isinstance(t, dict):
            raise CaptureError(f"Capture field 'truth' must be a dict; got {type(t).__name__}.")
        if "positions" not in t:
            raise CaptureError("Capture field 'truth' must hold 'positions' (M, 3).")
        pos = _as_float_array("truth/positions", t["positions"], ndim=2, shape=(None, 3))
        m = pos.shape[0]
        t["positions"] = pos
        for key, shp in (("normals", (m, 3)), ("areas", (m,)), ("albedo", (m,)),
                         ("specular", (m,)), ("exponent", (m,))):
            if key in t and t[key] is not None:
                t[key] = _as_float_array(f"truth/{key}", t[key], ndim=len(shp), shape=shp)
        if "visible" in t and t["visible"] is not None:
            vis = np.asarray(t["visible"]).astype(bool)
            if vis.shape != (m,):
                raise CaptureError(f"Capture field 'truth/visible' must have shape ({m},); got {vis.shape}.")
            t["visible"] = vis
        brdf = t.get("brdf", "lambertian")
        if brdf not in _TRUTH_BRDFS:
            raise CaptureError(f"Capture field 'truth' attribute 'brdf' must be one of {_TRUTH_BRDFS}; got {brdf!r}.")
        t["brdf"] = brdf

    # ------------------------------------------------------------------ views
    @property
    def is_full(self) -> bool:
        """True for a full STIR, False for paired/confocal traces."""
        return self.stir is not None

    @property
    def n_bins(self) -> int:
        return self.grid.n_bins

    def ill_ids(self) -> np.ndarray:
        """Ids of the illuminated patches (rows of the STIR)."""
        if self.illuminated_ids is not None:
            return self.illuminated_ids
        if self.stir is not None:
            return np.arange(self.stir.shape[0])
        return np.unique(self.pairs[:, 0])

    def obs_ids(self) -> np.ndarray:
        """Ids of the observed patches (columns of the STIR)."""
        if self.observed_ids is not None:
            return self.observed_ids
        if self.stir is not None:
            return np.arange(self.stir.shape[1])
        return np.unique(self.pairs[:, 1])

    def trace(self, illuminated_id: int, observed_id: int) -> np.ndarray:
        """The trace for pulse at ``illuminated_id`` seen from ``observed_id`` (ids, not rows)."""
        if self.stir is not None:
            ill, obs = self.ill_ids(), self.obs_ids()
            r = np.flatnonzero(ill == illuminated_id)
            c = np.flatnonzero(obs == observed_id)
            if r.size == 0 or c.size == 0:
                raise CaptureError(f"Unknown patch id: illuminated={illuminated_id} (known "
                                   f"{ill.tolist()[:20]}), observed={observed_id} (known {obs.tolist()[:20]}).")
            return self.stir[r[0], c[0]]
        hit = np.flatnonzero((self.pairs[:, 0] == illuminated_id) & (self.pairs[:, 1] == observed_id))
        if hit.size == 0:
            raise CaptureError(f"No trace for the pair (illuminated={illuminated_id}, "
                               f"observed={observed_id}); the capture holds {len(self.pairs)} pairs.")
        return self.traces[hit[0]]

    def as_pairs(self) -> tuple[np.ndarray, np.ndarray]:
        """``(traces, pairs)`` for either form (a full STIR is flattened row-major)."""
        if self.stir is None:
            return self.traces, self.pairs
        ill, obs = self.ill_ids(), self.obs_ids()
        ii, jj = np.meshgrid(ill, obs, indexing="ij")
        return (self.stir.reshape(-1, self.n_bins),
                np.stack([ii.ravel(), jj.ravel()], axis=1).astype(np.int64))

    # ------------------------------------------------------------------ file I/O
    def write(self, path: str | Path, inputs=()) -> Path:
        """Write the capture as HDF5 (format version 1, traces gzip-compressed one per chunk).

        The write is atomic: data go to a temporary file beside ``path`` that is fsync'ed and
        renamed over it, so a failure (disk full, a kill) leaves no truncated file and no earlier
        file changed. ``path`` is checked first (``stircasadi.io.check_output``; ``inputs`` are
        the files it must not be). Returns the path.
        """
        self.validate()
        path = check_output(path, inputs=inputs, what="capture")
        import h5py

        try:
            with atomic_path(path) as tmp:
                with h5py.File(tmp, "w") as f:
                    write_into(f, self)
        except (OSError, RuntimeError) as exc:  # h5py reports a failed flush as RuntimeError
            raise _write_error(path, exc) from exc
        return path

    @classmethod
    def read(cls, path: str | Path) -> "Capture":
        """Read and validate a Capture file; malformed files raise ``CaptureError`` naming the field."""
        import h5py

        path = Path(path)
        if not path.exists():
            raise CaptureError(f"Capture file not found: {path}.")
        try:
            f = h5py.File(path, "r")
        except OSError as exc:
            raise CaptureError(f"{path} is not a readable HDF5 file ({exc}). A Capture file is HDF5 "
                               "with attribute format='stircasadi.capture'; import other formats "
                               "with 'stircasadi import FILE --format ...'.") from exc
        with f:
            try:
                return read_from(f, source=str(path))
            except CaptureError:
                raise
            except (KeyError, ValueError, TypeError, OSError) as exc:
                raise CaptureError(f"{path}: corrupted Capture file ({type(exc).__name__}: {exc}).") from exc


# HDF5 storage lives in capture_io (it imports Capture); re-exported here for the package face.
from .capture_io import CaptureWriter, _write_error, read_from, write_into  # noqa: E402,F401

