"""Importers: existing recordings into a ``Capture`` (``stircasadi import FILE --format ...``).

When to use: data that were not captured by ``stircasadi acquire``. Every reader converts the
time axis to metres of optical path at this edge and states whether the times include the
source and camera legs (``legs_included``; rectified relay-wall data do not).

Formats (``FORMATS``):

========  ====================================================================================
ptu       PicoQuant PTU (via ptufile). T3 image: one trace per pixel (= illumination point);
          one channel -> confocal pairs (k, k); several channels -> full STIR, channel = observed
          patch. Otherwise the histogram of every channel: STIR (1, n_channels, n_bins).
          ``bin_width = tcspc_resolution * c``; bin 0 starts at the sync (``start = 0``).
phu       PicoQuant PHU histograms (via ptufile): curve k = observed k, STIR (1, n_curves, n_bins).
ytal      y-tal HDF5 (``tal/io/capture_data.py``): ``H`` time-first with ``H_format``
          (T_Sx_Sy=1, T_Lx_Ly_Sx_Sy=2, T_Si=3, T_Li_Si=4), ``delta_t`` and ``t_start`` in metres,
          ``t_accounts_first_and_last_bounces`` -> ``legs_included``; grids -> ``*_xyz``.
znlos     Zaragoza NLOS HDF5: ``data`` 5-D confocal ((sy, sx, bounces, t, colors) or (colors, t,
          bounces, sx, sy)) or 7-D exhaustive, colors and bounces summed; ``deltaT``, ``t0``
          (metres); the times include both legs.
csv       Header row; first column ``time_<unit>`` (unit s, ns, ps, m, mm) or ``time`` with
          ``time_unit=`` given; values are bin centres, uniformly spaced. Other columns are
          traces named ``ill<i>_obs<j>`` (pair (i, j)) or anything else (confocal (k, k)).
npz       ``stir`` or ``traces`` + ``pairs``; time axis as ``t`` (bin centres) or ``start`` +
          ``bin_width``, with ``time_unit`` (in the file or given).
stanford-lct, ccsocr, general-nlos
          the .mat readers of ``stircasadi.acquisition.nlos_mat`` (imported lazily).
========  ====================================================================================

Every failure is an ``ImportFormatError`` naming the file, the field, what is allowed and what
was found; NaN/inf and negative photon counts are refused, never passed on.

Neglects: PTU T2 mode (no sync, no histogram), y-tal ``scene_info`` (kept as a string).
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Callable

import numpy as np

from ..capture import FORMAT as CAPTURE_FORMAT
from ..capture import Capture
from ..constants import C
from ..errors import CaptureError, ImportFormatError, TimeGridError
from ..timegrid import TimeGrid

#: seconds (or metres) per unit, for time columns
TIME_UNITS = {"s": ("s", 1.0), "ms": ("s", 1e-3), "us": ("s", 1e-6), "ns": ("s", 1e-9),
              "ps": ("s", 1e-12), "fs": ("s", 1e-15), "m": ("m", 1.0), "mm": ("m", 1e-3)}

MAT_FORMATS = ("stanford-lct", "ccsocr", "general-nlos")


def _fail(path, what: str) -> ImportFormatError:
    return ImportFormatError(f"{path}: {what}")


def time_to_m(value, unit: str, path="<data>", field="time") -> np.ndarray:
    """Convert times in ``unit`` to metres of optical path."""
    u = str(unit).strip().lower().replace("µ", "u")
    if u not in TIME_UNITS:
        raise _fail(path, f"unknown time unit {unit!r} for {field}; allowed: {sorted(TIME_UNITS)}.")
    kind, f = TIME_UNITS[u]
    v = np.asarray(value, dtype=float) * f
    return v * C if kind == "s" else v


def _grid(path, start_m, width_m, n_bins) -> TimeGrid:
    try:
        return TimeGrid(float(start_m), float(width_m), int(n_bins))
    except (TimeGridError, TypeError, ValueError) as exc:
        raise _fail(path, f"time axis is invalid: {exc}") from exc


def _check_values(path, name: str, arr, counts: bool = False) -> np.ndarray:
    try:
        a = np.asarray(arr, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise _fail(path, f"{name} must be numeric; got {np.asarray(arr).dtype}.") from exc
    if a.size == 0:
        raise _fail(path, f"{name} is empty.")
    bad = ~np.isfinite(a)
    if bad.any():
        raise _fail(path, f"{name} holds {int(bad.sum())} NaN/inf value(s); every bin must be finite.")
    if counts and (a < 0).any():
        raise _fail(path, f"{name} holds {int((a < 0).sum())} negative photon count(s); counts are >= 0.")
    return a


def _capture(path, fmt: str, **kw) -> Capture:
    prov = kw.pop("provenance", {})
    prov = {"producer": f"stircasadi import --format {fmt}", "source_file": str(path),
            "source_format": fmt, **prov}
    try:
        return Capture(provenance=prov, **kw)
    except CaptureError as exc:
        raise _fail(path, f"does not make a valid Capture: {exc}") from exc


def _uniform_axis(path, t_m: np.ndarray) -> tuple[float, float]:
    """(start, bin_width) of a uniform axis of bin centres (metres)."""
    t_m = np.asarray(t_m, dtype=float)
    if t_m.ndim != 1 or t_m.size < 2:
        raise _fail(path, f"time axis needs >= 2 values; got shape {t_m.shape}.")
    if not np.all(np.isfinite(t_m)):
        raise _fail(path, "time axis holds NaN/inf.")
    d = np.diff(t_m)
    w = (t_m[-1] - t_m[0]) / (t_m.size - 1)
    if not w > 0 or np.any(np.abs(d - w) > 1e-6 * abs(w) + 1e-15):
        raise _fail(path, f"time axis must increase uniformly (one bin width); steps range "
                          f"{d.min():.6g}..{d.max():.6g} m.")
    return float(t_m[0] - 0.5 * w), float(w)


# ---------------------------------------------------------------------- PicoQuant
def _ptufile():
    try:
        import ptufile
    except ImportError as exc:  # pragma: no cover - dependency declared
        raise ImportFormatError("reading PTU/PHU needs the 'ptufile' package: pip install ptufile") from exc
    return ptufile


def capture_from_histograms(path, hist, resolution_s: float, fmt: str, image: bool = False,
                            legs_included: bool = True, provenance: dict | None = None) -> Capture:
    """Histogram counts -> Capture (shared by the PTU and PHU readers; testable without files).

    ``hist`` is ``(n_channels, n_bins)`` or, with ``image=True``, ``(n_pixels, n_channels, n_bins)``.
    """
    h = _check_values(path, "histogram", hist, counts=True)
    try:
        res = float(resolution_s)
    except (TypeError, ValueError):
        raise _fail(path, f"TCSPC resolution must be a number of seconds; got {resolution_s!r}.") from None
    if not (math.isfinite(res) and 0 < res < 1e-6):
        raise _fail(path, f"TCSPC resolution must be in (0, 1 us) seconds; got {resolution_s!r}.")
    grid = _grid(path, 0.0, res * C, h.shape[-1])
    prov = {"bin_width_ps": res * 1e12, **(provenance or {})}
    if image:
        if h.ndim != 3:
            raise _fail(path, f"image histogram must be (pixels, channels, bins); got {h.shape}.")
        if h.shape[1] == 1:
            n = h.shape[0]
            return _capture(path, fmt, grid=grid, traces=h[:, 0], pairs=np.stack([np.arange(n)] * 2, 1),
                            legs_included=legs_included, noise={"model": "poisson"}, provenance=prov)
        return _capture(path, fmt, grid=grid, stir=h, legs_included=legs_included,
                        noise={"model": "poisson"}, provenance=prov)
    if h.ndim != 2:
        raise _fail(path, f"histograms must be (channels, bins); got {h.shape}.")
    return _capture(path, fmt, grid=grid, stir=h[None], legs_included=legs_included,
                    noise={"model": "poisson"}, provenance=prov)


def read_ptu(path, legs_included: bool = True, **_) -> Capture:
    ptufile = _ptufile()
    try:
        f = ptufile.PtuFile(path)
    except Exception as exc:  # PqFileError, OSError, struct errors on corrupt files
        raise _fail(path, f"not a readable PicoQuant PTU file ({type(exc).__name__}: {exc}).") from exc
    with f:
        try:
            if not f.is_t3:
                raise _fail(path, "PTU file is T2 mode (no sync, no histogram); only T3 files hold "
                                  "time-of-flight histograms.")
            res = f.tcspc_resolution
            ident = {"ptu_record_type": str(f.record_type), "ptu_guid": str(f.guid),
                     "date_recorded": str(f.datetime)}
            if f.is_image:
                im = np.asarray(f.decode_image())  # (T, Y, X, C, H)
                if im.ndim != 5:
                    raise _fail(path, f"PTU image has dims {f.dims}; expected T, Y, X, C, H.")
                im = im.sum(axis=0)
                y, x, c, nb = im.shape
                return capture_from_histograms(path, im.reshape(y * x, c, nb), res, "ptu", image=True,
                                               legs_included=legs_included,
                                               provenance={**ident, "scan_shape": [y, x]})
            h = np.asarray(f.decode_histogram())
        except ImportFormatError:
            raise
        except Exception as exc:
            raise _fail(path, f"PTU records could not be decoded ({type(exc).__name__}: {exc}).") from exc
    return capture_from_histograms(path, h, res, "ptu", legs_included=legs_included, provenance=ident)


def read_phu(path, legs_included: bool = True, **_) -> Capture:
    ptufile = _ptufile()
    try:
        f = ptufile.PhuFile(path)
    except Exception as exc:
        raise _fail(path, f"not a readable PicoQuant PHU file ({type(exc).__name__}: {exc}).") from exc
    with f:
        try:
            hists = [np.asarray(h) for h in f.histograms()]
            res = list(f.histogram_resolutions)
        except Exception as exc:
            raise _fail(path, f"PHU histograms could not be decoded ({type(exc).__name__}: {exc}).") from exc
    return phu_to_capture(path, hists, res, legs_included)


def phu_to_capture(path, hists, resolutions, legs_included: bool = True) -> Capture:
    """PHU curves (list of 1-D counts) and their resolutions (s) -> Capture."""
    if len(hists) == 0:
        raise _fail(path, "PHU file holds no histogram.")
    lens = {np.asarray(h).shape for h in hists}
    if len(lens) != 1 or len(next(iter(lens))) != 1:
        raise _fail(path, f"PHU curves must be 1-D of one length to form a STIR; got shapes {sorted(lens)}.")
    if len(resolutions) != len(hists) or len({float(r) for r in resolutions}) != 1:
        raise _fail(path, f"PHU curves must share one resolution; got {list(resolutions)} s.")
    return capture_from_histograms(path, np.stack(hists), resolutions[0], "phu",
                                   legs_included=legs_included)


# ---------------------------------------------------------------------- HDF5 (y-tal, Zaragoza)
def _h5(path):
    import h5py
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise _fail(path, f"not a readable HDF5 file ({exc}).") from exc


def _scalar(path, f, key, default=None, required=True):
    import h5py
    if key not in f:
        if required:
            raise _fail(path, f"required field '{key}' is missing.")
        return default
    node = f[key]
    if not isinstance(node, h5py.Dataset):
        raise _fail(path, f"field '{key}' must be a dataset; found a group.")
    if node.shape is None:  # h5py.Empty
        return default
    v = np.asarray(node[()])
    if v.size != 1:
        raise _fail(path, f"field '{key}' must be a scalar; got shape {v.shape}.")
    v = v.reshape(()).item()
    if isinstance(v, bytes):
        v = v.decode("utf-8", "replace")
    return v


def _array(path, f, key, required=True):
    import h5py
    if key not in f:
        if required:
            raise _fail(path, f"required dataset '{key}' is missing.")
        return None
    node = f[key]
    if not isinstance(node, h5py.Dataset) or node.shape is None:
        if required:
            raise _fail(path, f"'{key}' must be a non-empty dataset.")
        return None
    return node[()]


def _xyz(path, name, arr, n=None):
    if arr is None:
        return None
    a = _check_values(path, name, arr)
    if a.shape[-1] != 3:
        if a.shape[0] == 3:
            a = np.moveaxis(a, 0, -1)
        else:
            raise _fail(path, f"{name} must have 3 coordinates on its last (or first) axis; got {a.shape}.")
    a = a.reshape(-1, 3)
    if n is not None and a.shape[0] != n:
        raise _fail(path, f"{name} holds {a.shape[0]} points; the data need {n}.")
    return a


def _finite_number(path, name, v):
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise _fail(path, f"'{name}' must be a number in metres; got {v!r}.") from None
    if not math.isfinite(x):
        raise _fail(path, f"'{name}' must be finite; got {v!r}.")
    return x


def read_ytal(path, **_) -> Capture:
    with _h5(path) as f:
        H = _check_values(path, "H", _array(path, f, "H"))
        hf = _scalar(path, f, "H_format")
        try:
            hf = int(hf)
        except (TypeError, ValueError):
            raise _fail(path, f"H_format must be an enum/int (1 T_Sx_Sy, 2 T_Lx_Ly_Sx_Sy, 3 T_Si, "
                              f"4 T_Li_Si); got {hf!r}.") from None
        dt = _finite_number(path, "delta_t", _scalar(path, f, "delta_t"))
        t0 = _scalar(path, f, "t_start", default=0.0, required=False)
        t0 = 0.0 if t0 is None else _finite_number(path, "t_start", t0)
        legs = _scalar(path, f, "t_accounts_first_and_last_bounces", default=None, required=False)
        if legs is None:
            raise _fail(path, "'t_accounts_first_and_last_bounces' is missing or empty; without it "
                              "the time origin is ambiguous. Set it in the file (True if the times "
                              "include the laser->wall and wall->sensor legs).")
        sgrid = _array(path, f, "sensor_grid_xyz", required=False)
        lgrid = _array(path, f, "laser_grid_xyz", required=False)
        sxyz = _array(path, f, "sensor_xyz", required=False)
        lxyz = _array(path, f, "laser_xyz", required=False)
    want_nd = {1: 3, 2: 5, 3: 2, 4: 3}
    if hf not in want_nd:
        raise _fail(path, f"H_format {hf} is not supported; allowed: 1 T_Sx_Sy, 2 T_Lx_Ly_Sx_Sy, "
                          "3 T_Si, 4 T_Li_Si.")
    if H.ndim != want_nd[hf]:
        raise _fail(path, f"H_format {hf} needs H with {want_nd[hf]} dimensions (time first); got "
                          f"shape {H.shape}.")
    nt = H.shape[0]
    grid = _grid(path, t0, dt, nt)
    data = np.moveaxis(H, 0, -1)  # time last
    src = _xyz(path, "laser_xyz", lxyz, 1)
    cam = _xyz(path, "sensor_xyz", sxyz, 1)
    common = dict(grid=grid, legs_included=bool(legs),
                  source_xyz=None if src is None else src[0], camera_xyz=None if cam is None else cam[0])
    if hf in (1, 3):
        traces = data.reshape(-1, nt)
        n = traces.shape[0]
        s = _xyz(path, "sensor_grid_xyz", sgrid, n)
        lg = None if lgrid is None else _xyz(path, "laser_grid_xyz", lgrid)
        confocal = lg is not None and s is not None and lg.shape == s.shape and np.allclose(lg, s)
        if confocal:
            ids = np.arange(n)
            return _capture(path, "ytal", traces=traces, pairs=np.stack([ids, ids], 1),
                            provenance={"confocal": True}, **common)
        if lg is not None and lg.shape[0] != 1:
            raise _fail(path, f"H_format {hf} with {lg.shape[0]} laser points that differ from the "
                              f"{n} sensor points is neither confocal nor single-laser.")
        return _capture(path, "ytal", stir=traces[None], observed_xyz=s, illuminated_xyz=lg, **common)
    if hf == 2:   # (Lx, Ly, Sx, Sy, T) -> (Lx*Ly, Sx*Sy, T)
        stir = data.reshape(data.shape[0] * data.shape[1], data.shape[2] * data.shape[3], nt)
    else:         # T_Li_Si: (Li, Si, T)
        stir = data
    lg = _xyz(path, "laser_grid_xyz", lgrid, stir.shape[0])
    s = _xyz(path, "sensor_grid_xyz", sgrid, stir.shape[1])
    return _capture(path, "ytal", stir=stir, illuminated_xyz=lg, observed_xyz=s, **common)


def _scan_grid(path, name, arr, scan_shape, transposed: bool) -> np.ndarray | None:
    """A Zaragoza grid (``cameraGridPositions`` / ``laserGridPositions``) as (n, 3) in the order of
    the capture's ids. The grid's scan axes come in the order of the data's scan axes in the file
    (as MATLAB wrote both; (3, A, B) or (A, B, 3)); ``transposed`` when the ids run over the
    second file axis first (as the traces are flattened)."""
    if arr is None:
        return None
    a = _check_values(path, name, arr)
    A, B = scan_shape
    if a.ndim == 3 and a.shape[0] == 3 and a.shape[1:] == (A, B):
        a = np.moveaxis(a, 0, -1)
    elif a.ndim == 2 and a.shape in ((A * B, 3), (3, A * B)):
        a = (a if a.shape[1] == 3 else a.T).reshape(A, B, 3)
    elif not (a.ndim == 3 and a.shape == (A, B, 3)):
        raise _fail(path, f"{name} must hold one 3-D point per scan position, shaped (3, {A}, {B}) or "
                          f"({A}, {B}, 3) like the data's scan axes; got {a.shape}.")
    if transposed:
        a = np.swapaxes(a, 0, 1)
    return a.reshape(-1, 3)


def read_znlos(path, **_) -> Capture:
    with _h5(path) as f:
        D = _check_values(path, "data", _array(path, f, "data"))
        dt = _finite_number(path, "deltaT", _scalar(path, f, "deltaT"))
        t0 = _finite_number(path, "t0", _scalar(path, f, "t0", default=0.0, required=False) or 0.0)
        cam = _array(path, f, "cameraPosition", required=False)
        las = _array(path, f, "laserPosition", required=False)
        cgrid = _array(path, f, "cameraGridPositions", required=False)
        lgrid = _array(path, f, "laserGridPositions", required=False)
    if D.ndim == 5:
        if D.shape[0] == D.shape[1]:
            H = np.moveaxis(D, [0, 1, 2, 3, 4], [3, 4, 1, 2, 0])   # (sy,sx,b,t,c) -> (c,b,t,sx,sy)
        elif D.shape[3] == D.shape[4]:
            H = np.moveaxis(D, [0, 1, 2, 3, 4], [0, 2, 1, 4, 3])   # (c,t,b,sx,sy) -> (c,b,t,sx,sy)
        else:
            raise _fail(path, f"5-D 'data' must be (sy, sx, bounces, t, colors) or (colors, t, bounces, "
                              f"sx, sy) with a square scan; got shape {D.shape}.")
        first = D.shape[0] == D.shape[1]
        scan = D.shape[:2] if first else D.shape[3:]
        H = H.sum(axis=(0, 1))           # (t, sx, sy)
        nt = H.shape[0]
        traces = np.moveaxis(H, 0, -1).reshape(-1, nt)
        n = traces.shape[0]
        ids = np.arange(n)
        grid = _grid(path, t0, dt, nt)
        # confocal: the illuminated and the observed point of trace i are the same wall point
        cg = _scan_grid(path, "cameraGridPositions", cgrid, scan, transposed=not first)
        return _capture(path, "znlos", grid=grid, traces=traces, pairs=np.stack([ids, ids], 1),
                        legs_included=True, observed_xyz=cg, illuminated_xyz=cg,
                        source_xyz=None if las is None else _xyz(path, "laserPosition", las, 1)[0],
                        camera_xyz=None if cam is None else _xyz(path, "cameraPosition", cam, 1)[0],
                        provenance={"confocal": True,
                                    "grid_points": 0 if cg is None else int(cg.shape[0])})
    if D.ndim == 7:
        if D.shape[4] == 6:
            H = np.moveaxis(D, list(range(7)), (4, 3, 6, 5, 1, 2, 0))
        elif D.shape[2] == 6:
            H = np.moveaxis(D, list(range(7)), (0, 2, 1, 6, 5, 4, 3))
        else:
            raise _fail(path, f"7-D 'data' must have its 6 bounce orders on axis 4 (ly, lx, sy, sx, "
                              f"bounces, t, colors) or axis 2 (colors, t, bounces, sx, sy, lx, ly); "
                              f"got shape {D.shape}.")
        first = D.shape[4] == 6
        lscan, cscan = (D.shape[0:2], D.shape[2:4]) if first else (D.shape[5:7], D.shape[3:5])
        H = H.sum(axis=(0, 1))           # (t, lx, ly, sx, sy)
        nt = H.shape[0]
        stir = np.moveaxis(H, 0, -1)
        stir = stir.reshape(stir.shape[0] * stir.shape[1], stir.shape[2] * stir.shape[3], nt)
        # both scan pairs are flattened second-file-axis first (see the moveaxis above)
        lg = _scan_grid(path, "laserGridPositions", lgrid, lscan, transposed=True)
        cg = _scan_grid(path, "cameraGridPositions", cgrid, cscan, transposed=True)
        return _capture(path, "znlos", grid=_grid(path, t0, dt, nt), stir=stir, legs_included=True,
                        illuminated_xyz=lg, observed_xyz=cg,
                        source_xyz=None if las is None else _xyz(path, "laserPosition", las, 1)[0],
                        camera_xyz=None if cam is None else _xyz(path, "cameraPosition", cam, 1)[0])
    raise _fail(path, f"'data' must be 5-D (confocal) or 7-D (exhaustive); got {D.ndim}-D {D.shape}.")


# ---------------------------------------------------------------------- CSV / NPZ
_PAIR = re.compile(r"^ill(\d+)_obs(\d+)$")


def _pairs_from_names(names: list[str]) -> np.ndarray:
    m = [_PAIR.match(n.strip()) for n in names]
    if all(m):
        return np.array([[int(x.group(1)), int(x.group(2))] for x in m], dtype=np.int64)
    ids = np.arange(len(names))
    return np.stack([ids, ids], 1)


def read_csv(path, time_unit: str | None = None, legs_included: bool = True, **_) -> Capture:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise _fail(path, f"cannot read as UTF-8 text ({exc}).") from exc
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 3:
        raise _fail(path, "a trace CSV needs a header row and >= 2 data rows.")
    header = [h.strip() for h in lines[0].split(",")]
    if len(header) < 2:
        raise _fail(path, f"header must be 'time_<unit>,<trace>,...' with >= 1 trace column; got {lines[0]!r}.")
    m = re.match(r"^(?:t|time)(?:_(\w+)|\s*\[(\w+)\])?$", header[0], re.IGNORECASE)
    if not m:
        raise _fail(path, f"first column must be the time axis named 'time_<unit>' (e.g. time_ps); "
                          f"got {header[0]!r}.")
    unit = m.group(1) or m.group(2) or time_unit
    if unit is None:
        raise _fail(path, "the time unit is not stated: name the column time_ps/time_ns/time_s/time_m "
                          "or pass --time-unit.")
    if time_unit is not None and m.group(1 if m.group(1) else 2) and unit.lower() != time_unit.lower():
        raise _fail(path, f"time unit in the header ({unit!r}) contradicts --time-unit {time_unit!r}.")
    rows = []
    for k, ln in enumerate(lines[1:], start=2):
        cells = ln.split(",")
        if len(cells) != len(header):
            raise _fail(path, f"row {k} has {len(cells)} columns; the header has {len(header)}.")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise _fail(path, f"row {k} holds a non-number: {ln[:80]!r}.") from None
    a = np.array(rows)
    start, width = _uniform_axis(path, time_to_m(a[:, 0], unit, path))
    traces = _check_values(path, "traces", a[:, 1:].T)
    return _capture(path, "csv", grid=_grid(path, start, width, a.shape[0]), traces=traces,
                    pairs=_pairs_from_names(header[1:]), legs_included=legs_included,
                    provenance={"time_unit": unit, "columns": ",".join(header[1:])[:2000]})


def read_npz(path, time_unit: str | None = None, legs_included: bool | None = None, **_) -> Capture:
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise _fail(path, f"not a readable .npz archive ({type(exc).__name__}: {exc}).") from exc
    with z:
        keys = set(z.files)
        unit = str(z["time_unit"]) if "time_unit" in keys else time_unit
        if unit is None:
            raise _fail(path, "the time unit is not stated: store 'time_unit' (s, ns, ps, m...) in the "
                              "archive or pass --time-unit.")
        if time_unit is not None and "time_unit" in keys and unit.lower() != time_unit.lower():
            raise _fail(path, f"archive says time_unit={unit!r} but --time-unit {time_unit!r} was given.")
        if "stir" in keys:
            data = _check_values(path, "stir", z["stir"])
            if data.ndim != 3:
                raise _fail(path, f"'stir' must be (n_illuminated, n_observed, n_bins); got {data.shape}.")
            kw = {"stir": data}
        elif "traces" in keys and "pairs" in keys:
            data = _check_values(path, "traces", z["traces"])
            kw = {"traces": data, "pairs": z["pairs"]}
        else:
            raise _fail(path, f"archive must hold 'stir' or 'traces' + 'pairs'; found {sorted(keys)}.")
        n_bins = data.shape[-1]
        if "t" in keys:
            start, width = _uniform_axis(path, time_to_m(z["t"], unit, path, "t"))
            if np.asarray(z["t"]).size != n_bins:
                raise _fail(path, f"'t' has {np.asarray(z['t']).size} values but the data have {n_bins} bins.")
        elif "start" in keys and "bin_width" in keys:
            start = float(time_to_m(z["start"], unit, path, "start"))
            width = float(time_to_m(z["bin_width"], unit, path, "bin_width"))
        else:
            raise _fail(path, "the time axis is missing: store 't' (bin centres) or 'start' and "
                              "'bin_width'.")
        legs = bool(z["legs_included"]) if "legs_included" in keys else \
            (True if legs_included is None else legs_included)
    return _capture(path, "npz", grid=_grid(path, start, width, n_bins), legs_included=legs,
                    provenance={"time_unit": unit}, **kw)


# ---------------------------------------------------------------------- .mat (lazy)
def _mat_reader(name: str) -> Callable:
    def read(path, **opts) -> Capture:
        try:
            from . import nlos_mat
        except ImportError as exc:
            raise ImportFormatError(f"format {name!r} needs stircasadi.acquisition.nlos_mat, which is "
                                    f"not available ({exc}).") from exc
        fn = getattr(nlos_mat, "read_" + name.replace("-", "_"), None)
        if fn is not None:
            import inspect
            params = inspect.signature(fn).parameters
            unused = [k for k, v in opts.items() if k not in params and v is not None
                      and k not in ("legs_included", "time_unit")]
            if unused:
                raise ImportFormatError(f"format {name!r} does not take option(s) {unused}; it takes "
                                        f"{[k for k in params if k != 'path']}.")
            return fn(path, **{k: v for k, v in opts.items() if k in params and v is not None})
        if hasattr(nlos_mat, "read"):
            return nlos_mat.read(path, name, **opts)
        raise ImportFormatError(f"stircasadi.acquisition.nlos_mat has no reader for {name!r}.")
    read.__name__ = "read_" + name.replace("-", "_")
    return read


#: format name -> (reader, one-line description)
FORMATS: dict[str, tuple[Callable, str]] = {
    "stanford-lct": (_mat_reader("stanford-lct"), "confocal rect_data + width .mat (O'Toole 2018)"),
    "ccsocr": (_mat_reader("ccsocr"), "sub_Sig + C_i/C_d .mat (CC-SOCR)"),
    "general-nlos": (_mat_reader("general-nlos"), "raw paired counts + setup.mat (general-NLOS)"),
    "ytal": (read_ytal, "y-tal HDF5 (H, H_format, delta_t, t_start)"),
    "znlos": (read_znlos, "Zaragoza NLOS HDF5 (data, deltaT, t0)"),
    "ptu": (read_ptu, "PicoQuant PTU (T3 histograms / images)"),
    "phu": (read_phu, "PicoQuant PHU histograms"),
    "csv": (read_csv, "CSV: time_<unit> column + one column per trace"),
    "npz": (read_npz, "NumPy .npz: stir or traces+pairs, t or start+bin_width, time_unit"),
}


def format_list() -> str:
    return ", ".join(FORMATS)


def detect_format(path) -> str:
    """Detect the format of ``path`` from its extension and content; refuse unknown files."""
    p = Path(path)
    if not p.exists():
        raise ImportFormatError(f"{p}: file not found.")
    ext = p.suffix.lower()
    if ext in (".ptu", ".phu", ".csv", ".npz"):
        return ext[1:]
    if ext in (".h5", ".hdf5", ".hdf"):
        import h5py
        try:
            with h5py.File(p, "r") as f:
                keys = set(f.keys())
                fmt = f.attrs.get("format")
        except OSError as exc:
            raise ImportFormatError(f"{p}: not a readable HDF5 file ({exc}).") from exc
        if fmt in (CAPTURE_FORMAT, CAPTURE_FORMAT.encode()):
            raise ImportFormatError(f"{p} is already a stircasadi Capture; use it directly (no import needed).")
        if "H" in keys and "delta_t" in keys:
            return "ytal"
        if "data" in keys and "deltaT" in keys:
            return "znlos"
        raise ImportFormatError(f"{p}: HDF5 layout not recognised (top-level keys {sorted(keys)[:12]}); "
                                f"known formats: {format_list()}. Pass --format.")
    if ext == ".mat":
        try:
            from . import nlos_mat
            found = nlos_mat.detect(p)
            if found in MAT_FORMATS:
                return found
        except ImportError:  # pragma: no cover - nlos_mat ships with the package
            pass
        except Exception:  # fall back to the variable names below
            pass
        try:
            from scipy.io import whosmat
            names = {n for n, _, _ in whosmat(str(p))}
        except Exception as exc:
            raise ImportFormatError(f"{p}: not a readable MATLAB file ({exc}).") from exc
        if "rect_data" in names:
            return "stanford-lct"
        if "sub_Sig" in names:
            return "ccsocr"
        if "counts" in names or {"laserpoints", "detectpoints"} & names:
            return "general-nlos"
        raise ImportFormatError(f"{p}: MATLAB variables {sorted(names)[:12]} match no known layout; "
                                f"known formats: {format_list()}. Pass --format.")
    raise ImportFormatError(f"{p}: cannot tell the format from extension {ext or '(none)'!r}; known "
                            f"formats: {format_list()}. Pass --format.")


def import_file(path, fmt: str | None = None, **options) -> Capture:
    """Read ``path`` in format ``fmt`` (detected when None) and return a validated Capture."""
    if fmt is None:
        fmt = detect_format(path)
    if fmt not in FORMATS:
        raise ImportFormatError(f"unknown format {fmt!r}; allowed: {format_list()}.")
    if not Path(path).exists():
        raise ImportFormatError(f"{path}: file not found.")
    reader = FORMATS[fmt][0]
    try:
        return reader(path, **options)
    except (ImportFormatError, CaptureError):
        raise
    except (KeyError, ValueError, TypeError, IndexError, OSError) as exc:
        raise ImportFormatError(f"{path}: could not be read as {fmt!r} ({type(exc).__name__}: {exc}).") from exc
