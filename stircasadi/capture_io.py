"""HDF5 storage of a ``Capture`` (format ``stircasadi.capture`` version 1): the header written
once (``_write_header``), traces one per chunk compressed only where it pays (``_compresses``),
the streaming ``CaptureWriter`` the acquisition session appends rows with, and ``read_from``.

``Capture.write`` / ``Capture.read`` (``stircasadi.capture``) are the entry points; this module
holds what they and the session share.
"""
from __future__ import annotations

import datetime as _dt
import re
from pathlib import Path
from typing import Any

import numpy as np

from .capture import FORMAT, VERSION, _KNOWN_DATASETS, _KNOWN_GROUPS, Capture, _as_float_array
from .errors import CaptureError, OutputError
from .io import atomic_path, check_output
from .timegrid import TimeGrid

__all__ = ["CaptureWriter", "write_into", "read_from"]


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
