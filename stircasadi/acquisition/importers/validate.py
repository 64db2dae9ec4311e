"""The one set of validators every importer uses: numbers, time axes, points, .mat fields.

When to use: inside a format module, to turn a field of a file into a checked array or a time
grid. Every failure is an ``ImportFormatError`` naming the file, the field, what is allowed and
what was found; NaN/inf and negative photon counts are refused, never passed on.

Units at this edge: ``time_to_m`` converts a time in seconds-like units to metres of optical
path (``t * c``) and passes metres through; ``uniform_axis`` turns bin centres into the
``(start, bin_width)`` of a ``TimeGrid`` (``start = t_0 - w/2``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ...capture import Capture
from ...constants import C
from ...errors import CaptureError, ImportFormatError, TimeGridError
from ...timegrid import TimeGrid

#: seconds (or metres) per unit, for time columns
TIME_UNITS = {"s": ("s", 1.0), "ms": ("s", 1e-3), "us": ("s", 1e-6), "ns": ("s", 1e-9),
              "ps": ("s", 1e-12), "fs": ("s", 1e-15), "m": ("m", 1.0), "mm": ("m", 1e-3)}


def fail(path, what: str) -> ImportFormatError:
    """The error of a file that cannot be imported: ``<path>: <what>``."""
    return ImportFormatError(f"{path}: {what}")


def time_to_m(value, unit: str, path="<data>", field="time") -> np.ndarray:
    """Convert times in ``unit`` to metres of optical path."""
    u = str(unit).strip().lower().replace("µ", "u")
    if u not in TIME_UNITS:
        raise fail(path, f"unknown time unit {unit!r} for {field}; allowed: {sorted(TIME_UNITS)}.")
    kind, f = TIME_UNITS[u]
    v = np.asarray(value, dtype=float) * f
    return v * C if kind == "s" else v


def grid(path, start_m, width_m, n_bins) -> TimeGrid:
    """A ``TimeGrid`` whose failure names the file."""
    try:
        return TimeGrid(float(start_m), float(width_m), int(n_bins))
    except (TimeGridError, TypeError, ValueError) as exc:
        raise fail(path, f"time axis is invalid: {exc}") from exc


def check_values(path, name: str, arr, counts: bool = False) -> np.ndarray:
    """``arr`` as finite float64 (and >= 0 when ``counts``); refuses empty, text, NaN/inf."""
    raw = np.asarray(arr)
    if raw.dtype.kind not in "biuf":
        raise fail(path, f"{name} must be numeric; got dtype {raw.dtype}.")
    a = raw.astype(np.float64)
    if a.size == 0:
        raise fail(path, f"{name} is empty.")
    bad = ~np.isfinite(a)
    if bad.any():
        raise fail(path, f"{name} holds {int(bad.sum())} NaN/inf value(s); every bin must be finite.")
    if counts and (a < 0).any():
        raise fail(path, f"{name} holds {int((a < 0).sum())} negative photon count(s); counts are >= 0.")
    return a


def finite_number(path, name, v) -> float:
    """One finite number (metres, seconds...) or a clear error."""
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise fail(path, f"'{name}' must be a number in metres; got {v!r}.") from None
    if not math.isfinite(x):
        raise fail(path, f"'{name}' must be finite; got {v!r}.")
    return x


def xyz(path, name, arr, n=None) -> np.ndarray | None:
    """Points as ``(n, 3)`` metres (coordinates on the last or first axis); None passes through."""
    if arr is None:
        return None
    a = check_values(path, name, arr)
    if a.shape[-1] != 3:
        if a.shape[0] == 3:
            a = np.moveaxis(a, 0, -1)
        else:
            raise fail(path, f"{name} must have 3 coordinates on its last (or first) axis; got {a.shape}.")
    a = a.reshape(-1, 3)
    if n is not None and a.shape[0] != n:
        raise fail(path, f"{name} holds {a.shape[0]} points; the data need {n}.")
    return a


def uniform_axis(path, t_m: np.ndarray) -> tuple[float, float]:
    """(start, bin_width) of a uniform axis of bin centres (metres)."""
    t_m = np.asarray(t_m, dtype=float)
    if t_m.ndim != 1 or t_m.size < 2:
        raise fail(path, f"time axis needs >= 2 values; got shape {t_m.shape}.")
    if not np.all(np.isfinite(t_m)):
        raise fail(path, "time axis holds NaN/inf.")
    d = np.diff(t_m)
    w = (t_m[-1] - t_m[0]) / (t_m.size - 1)
    if not w > 0 or np.any(np.abs(d - w) > 1e-6 * abs(w) + 1e-15):
        raise fail(path, f"time axis must increase uniformly (one bin width); steps range "
                         f"{d.min():.6g}..{d.max():.6g} m.")
    return float(t_m[0] - 0.5 * w), float(w)


def make_capture(path, fmt: str, **kw) -> Capture:
    """A validated ``Capture`` with the import's provenance; a Capture error names the file."""
    prov = kw.pop("provenance", {})
    prov = {"producer": f"stircasadi import --format {fmt}", "source_file": str(path),
            "source_format": fmt, **prov}
    try:
        return Capture(provenance=prov, **kw)
    except CaptureError as exc:
        raise fail(path, f"does not make a valid Capture: {exc}") from exc


# ---------------------------------------------------------------------- MATLAB .mat fields
def loadmat(path: Path, fmt: str) -> dict:
    """A MATLAB v5 file as a dict (v7.3/HDF5 and garbage refused clearly)."""
    import scipy.io as sio

    if not path.exists():
        raise ImportFormatError(f"{fmt}: file not found: {path}.")
    try:
        return sio.loadmat(str(path))
    except NotImplementedError as exc:  # MATLAB v7.3 (HDF5) files
        raise ImportFormatError(f"{fmt}: {path} is a MATLAB v7.3 (HDF5) file; this importer reads "
                                "MATLAB v5 .mat files. Re-save it with save(..., '-v7') in MATLAB.") from exc
    except Exception as exc:  # scipy raises ValueError/TypeError/OSError on garbage
        raise ImportFormatError(f"{fmt}: {path} is not a readable MATLAB v5 .mat file "
                                f"({type(exc).__name__}: {exc}).") from exc


def mat_field(d: dict, name: str, path: Path, fmt: str, ndim: int | None = None,
              shape: tuple | None = None) -> np.ndarray:
    """A numeric field of a loaded .mat file, with its dimensions and shape checked."""
    if name not in d:
        keys = sorted(k for k in d if not k.startswith("__"))
        raise ImportFormatError(f"{fmt}: {path} has no field '{name}'; found {keys}. "
                                f"A {fmt} file must hold '{name}'.")
    arr = np.asarray(d[name])
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise ImportFormatError(f"{fmt}: field '{name}' in {path} must be numeric; got dtype {arr.dtype}.")
    if ndim is not None and arr.ndim != ndim:
        raise ImportFormatError(f"{fmt}: field '{name}' in {path} must have {ndim} dimensions; "
                                f"got shape {arr.shape}.")
    if shape is not None:
        for want, got in zip(shape, arr.shape):
            if want is not None and want != got:
                raise ImportFormatError(f"{fmt}: field '{name}' in {path} must have shape {shape} "
                                        f"(None = any); got {arr.shape}.")
    if arr.size == 0:
        raise ImportFormatError(f"{fmt}: field '{name}' in {path} is empty.")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise ImportFormatError(f"{fmt}: field '{name}' in {path} holds NaN/inf values.")
    return arr


def counts(arr: np.ndarray, name: str, path: Path, fmt: str) -> np.ndarray:
    """Photon counts as float64, refusing negative values."""
    out = arr.astype(np.float64)
    if np.any(out < 0):
        raise ImportFormatError(f"{fmt}: field '{name}' in {path} holds negative photon counts "
                                f"(min {out.min():g}); counts must be >= 0.")
    return out


def mat_names(path: Path) -> set:
    """Variable names of a .mat file (empty when unreadable): for the sniffers."""
    try:
        from scipy.io import whosmat
        return {v[0] for v in whosmat(str(path))}
    except Exception:
        return set()


def h5_keys(path: Path) -> tuple[set, dict] | None:
    """Top-level keys and attributes of an HDF5 file (None when unreadable): for the sniffers."""
    import h5py
    try:
        with h5py.File(path, "r") as f:
            return set(f.keys()), dict(f.attrs)
    except Exception:
        return None


# ---------------------------------------------------------------------- HDF5 fields
def open_h5(path):
    """An HDF5 file open for reading, or a clear error."""
    import h5py
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise fail(path, f"not a readable HDF5 file ({exc}).") from exc


def scalar(path, f, key, default=None, required=True):
    """A scalar dataset (enum, number, bool, text); an empty one is ``default``."""
    import h5py
    if key not in f:
        if required:
            raise fail(path, f"required field '{key}' is missing.")
        return default
    node = f[key]
    if not isinstance(node, h5py.Dataset):
        raise fail(path, f"field '{key}' must be a dataset; found a group.")
    if node.shape is None:  # h5py.Empty
        return default
    v = np.asarray(node[()])
    if v.size != 1:
        raise fail(path, f"field '{key}' must be a scalar; got shape {v.shape}.")
    v = v.reshape(()).item()
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    return v


def array(path, f, key, required=True):
    """A dataset's array; None when absent or empty and not required."""
    import h5py
    if key not in f:
        if required:
            raise fail(path, f"required dataset '{key}' is missing.")
        return None
    node = f[key]
    if not isinstance(node, h5py.Dataset) or node.shape is None:
        if required:
            raise fail(path, f"'{key}' must be a non-empty dataset.")
        return None
    return node[()]
