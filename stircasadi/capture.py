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

import datetime as _dt
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import CaptureError, OutputError
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


def _write_error(path, exc: BaseException) -> OutputError:
    """One line saying why an HDF5 write failed (HDF5's own message spans many lines)."""
    text = str(exc)
    m = re.search(r"error message = '([^']*)'", text)
    why = m.group(1) if m else " ".join(text.split())[:200]
    return OutputError(f"Could not write the capture {path}: {why}. Nothing was changed at that "
                       "path; free disk space or choose another location.")


def _attrs_to_dict(attrs) -> dict:
    out = {}
    for k, v in attrs.items():
        if isinstance(v, bytes):
            v = v.decode("utf-8", "replace")
        elif isinstance(v, np.ndarray) and v.ndim == 0:
            v = v.item()
        elif isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


def _write_attrs(group, d: dict) -> None:
    for k, v in d.items():
        if v is None:
            continue
        if isinstance(v, (dict, list, tuple)) and not (isinstance(v, (list, tuple)) and
                                                       all(isinstance(x, (int, float)) for x in v)):
            import json
            v = json.dumps(v, default=str)
        group.attrs[k] = v


#: HDF5 storage of the trace data: gzip + byte shuffle (float64 traces compress 5-15x)
_COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
#: smallest chunk, bytes: traces shorter than this are grouped so the chunk index stays small
_MIN_CHUNK_BYTES = 4096


def _chunks(shape: tuple) -> tuple:
    """One trace per chunk (time last), grouping short traces along the axis before time."""
    nb = int(shape[-1])
    group = max(1, min(int(shape[-2]) if len(shape) > 1 else 1, _MIN_CHUNK_BYTES // (8 * nb)))
    return (1,) * (len(shape) - 2) + ((group,) if len(shape) > 1 else ()) + (nb,)


def _write_header(f, cap: Capture) -> None:
    """Everything of ``cap`` except its trace data (``stir`` / ``traces``): the one place that
    writes the Capture header, used by ``write_into`` and ``CaptureWriter``."""
    f.attrs["format"] = FORMAT
    f.attrs["version"] = VERSION
    f.attrs["start_m"] = cap.grid.start
    f.attrs["bin_width_m"] = cap.grid.bin_width
    f.attrs["legs_included"] = bool(cap.legs_included)
    for name in _KNOWN_DATASETS:
        v = getattr(cap, name)
        if v is not None and name not in ("stir", "traces"):
            f.create_dataset(name, data=v)
    if cap.noise:
        g = f.create_group("noise")
        _write_attrs(g, cap.noise)
    if cap.truth is not None:
        g = f.create_group("truth")
        for k, v in cap.truth.items():
            if k == "brdf":
                g.attrs["brdf"] = v
            elif v is not None and not isinstance(v, str):
                g.create_dataset(k, data=np.asarray(v))
    prov = dict(cap.provenance)
    prov.setdefault("producer", "stircasadi")
    prov.setdefault("date", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
    g = f.create_group("provenance")
    _write_attrs(g, prov)
    for key, val in cap.extras.items():
        _write_extra(f, key, val)


def _compresses(data: np.ndarray, n_sample: int = 16) -> bool:
    """Whether gzip+shuffle saves >= 25 % on a sample of traces (counts do, 5-15x; float noise
    does not, and compressing it costs seconds for nothing)."""
    import zlib

    flat = data.reshape(-1, data.shape[-1])
    rows = flat[np.linspace(0, flat.shape[0] - 1, min(n_sample, flat.shape[0])).astype(int)]
    raw = np.ascontiguousarray(rows, dtype="<f8").view(np.uint8).reshape(-1, 8).T.tobytes()
    return len(zlib.compress(raw, 1)) < 0.75 * len(raw)


def _create_data(f, name: str, shape: tuple, data=None):
    """The trace dataset: chunked one trace per chunk, gzip+shuffle unless the data do not compress."""
    opts = _COMPRESSION if data is None or _compresses(data) else {}
    return f.create_dataset(name, shape=shape, dtype="f8", data=data, chunks=_chunks(shape), **opts)


def write_into(f, cap: Capture) -> None:
    """Write ``cap`` into an open, empty h5py File/Group (header, then the compressed data)."""
    _write_header(f, cap)
    name = "stir" if cap.stir is not None else "traces"
    data = getattr(cap, name)
    _create_data(f, name, data.shape, data)


class CaptureWriter:
    """Write a full-STIR Capture row by row: the header once, then ``stir[r]`` as rows arrive.

    The file is built under a temporary name beside ``path`` and renamed over it only by
    :meth:`commit` (fsync'ed, atomic); leaving the ``with`` block by an exception removes it and
    leaves ``path`` untouched. Every row must be written before the commit. Memory stays one row.

    Parameters
    ----------
    path : the Capture file to produce.
    grid : TimeGrid of the rows.
    n_illuminated, n_observed : int, the STIR's first two axes.
    **fields : the other ``Capture`` fields (``legs_included``, ``illuminated_ids``, ``noise``,
        ``provenance``, ``extras``...), validated as a Capture would validate them.

    Example
    -------
    >>> with CaptureWriter("cap.h5", grid, 3, 2, noise={"model": "poisson"}) as w:  # doctest: +SKIP
    ...     for r in range(3):
    ...         w.write_row(r, row(r))
    ...     w.commit()
    """

    def __init__(self, path, grid: TimeGrid, n_illuminated: int, n_observed: int, **fields):
        self.path = check_output(path, what="capture")
        self.shape = (int(n_illuminated), int(n_observed), grid.n_bins)
        # validates every field against the shape without allocating the STIR
        self.template = Capture(grid=grid, stir=np.broadcast_to(np.zeros(1), self.shape), **fields)
        self._written = np.zeros(self.shape[0], dtype=bool)
        self._ctx = self._file = self._data = None

    def __enter__(self) -> "CaptureWriter":
        import h5py

        self._ctx = atomic_path(self.path)
        tmp = self._ctx.__enter__()
        try:
            self._file = h5py.File(tmp, "w")
            _write_header(self._file, self.template)
            self._data = _create_data(self._file, "stir", self.shape)
        except (OSError, RuntimeError) as exc:
            self._abort(exc)
            raise _write_error(self.path, exc) from exc
        except BaseException as exc:
            self._abort(exc)
            raise
        return self

    def write_row(self, r: int, row) -> None:
        """Write ``stir[r] = row`` (``(n_observed, n_bins)``, finite float64)."""
        row = _as_float_array(f"stir[{r}]", row, ndim=2, shape=self.shape[1:])
        try:
            self._data[int(r)] = row
        except (OSError, RuntimeError) as exc:
            raise _write_error(self.path, exc) from exc
        self._written[int(r)] = True

    def commit(self) -> Path:
        """Close the file and rename it over ``path`` (all rows must have been written)."""
        missing = np.flatnonzero(~self._written)
        if missing.size:
            raise CaptureError(f"CaptureWriter.commit: rows {missing[:10].tolist()} of {self.shape[0]} "
                               "were never written; a Capture holds no invented zeros.")
        try:
            self._file.close()
            self._file = None
            ctx, self._ctx = self._ctx, None
            ctx.__exit__(None, None, None)
        except (OSError, RuntimeError) as exc:
            self._file = None
            raise _write_error(self.path, exc) from exc
        return self.path

    def _abort(self, exc) -> None:
        if self._file is not None:
            try:
                self._file.close()
            except Exception:  # pragma: no cover - already broken
                pass
            self._file = None
        if self._ctx is not None:
            ctx, self._ctx = self._ctx, None
            try:
                ctx.__exit__(type(exc), exc, None)
            except BaseException:
                pass

    def __exit__(self, etype, exc, tb) -> None:
        if self._ctx is not None:
            self._abort(exc if exc is not None else CaptureError("CaptureWriter closed without commit()"))


def _write_extra(f, key: str, val) -> None:
    if isinstance(val, dict) and "__attrs__" in val:
        g = f.require_group(key)
        _write_attrs(g, val["__attrs__"])
        for k, v in val.items():
            if k != "__attrs__":
                _write_extra(g, k, v)
    elif key.startswith("@"):
        f.attrs[key[1:]] = val
    else:
        f.create_dataset(key, data=val)


def _read_extra(node) -> Any:
    import h5py

    if isinstance(node, h5py.Group):
        d = {"__attrs__": _attrs_to_dict(node.attrs)}
        for k in node:
            d[k] = _read_extra(node[k])
        return d
    return node[()]


def read_from(f, source: str = "<h5>") -> Capture:
    """Build a ``Capture`` from an open h5py File/Group (inverse of ``write_into``)."""
    import h5py

    attrs = _attrs_to_dict(f.attrs)
    if attrs.get("format") != FORMAT:
        raise CaptureError(f"{source}: attribute 'format' must be {FORMAT!r}; got "
                           f"{attrs.get('format')!r}. Import other formats with 'stircasadi import'.")
    version = attrs.get("version")
    if version != VERSION:
        raise CaptureError(f"{source}: attribute 'version' must be {VERSION}; got {version!r}.")
    for key in ("start_m", "bin_width_m", "legs_included"):
        if key not in attrs:
            raise CaptureError(f"{source}: required attribute '{key}' is missing.")
    kw: dict[str, Any] = {}
    for name in _KNOWN_DATASETS:
        if name in f:
            if not isinstance(f[name], h5py.Dataset):
                raise CaptureError(f"{source}: '{name}' must be a dataset, found a group.")
            kw[name] = f[name][()]
    ref = kw.get("stir", kw.get("traces"))
    if ref is None:
        raise CaptureError(f"{source}: neither dataset 'stir' nor 'traces' is present; a Capture "
                           "needs one of them.")
    ref = np.asarray(ref)
    if ref.ndim < 1:
        raise CaptureError(f"{source}: dataset {'stir' if 'stir' in kw else 'traces'} is a scalar.")
    try:
        grid = TimeGrid(attrs["start_m"], attrs["bin_width_m"], int(ref.shape[-1]))
    except Exception as exc:  # TimeGridError carries the reason
        raise CaptureError(f"{source}: attributes start_m/bin_width_m are invalid: {exc}") from exc
    noise = _attrs_to_dict(f["noise"].attrs) if "noise" in f else {}
    prov = _attrs_to_dict(f["provenance"].attrs) if "provenance" in f else {}
    truth = None
    if "truth" in f:
        g = f["truth"]
        truth = {k: g[k][()] for k in g if isinstance(g[k], h5py.Dataset)}
        truth["brdf"] = _attrs_to_dict(g.attrs).get("brdf", "lambertian")
    extras = {}
    for k in f:
        if k not in _KNOWN_DATASETS and k not in _KNOWN_GROUPS:
            extras[k] = _read_extra(f[k])
    for k, v in attrs.items():
        if k not in ("format", "version", "start_m", "bin_width_m", "legs_included"):
            extras["@" + k] = v
    try:
        return Capture(grid=grid, legs_included=attrs["legs_included"], noise=noise,
                       provenance=prov, truth=truth, extras=extras, **kw)
    except CaptureError as exc:
        raise CaptureError(f"{source}: {exc}") from exc
