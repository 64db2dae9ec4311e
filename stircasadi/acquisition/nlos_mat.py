"""Importers for the public relay-wall NLOS datasets stored as MATLAB .mat files.

When to use: to turn a published confocal or paired relay-wall scan into a ``Capture`` so the
geometry stage (``stircasadi.geometry.relay``) can run on it. Formats:

``stanford-lct``  O'Toole, Lindell & Wetzstein 2018 (Nature 555, 338): ``rect_data`` uint16
                  (N, N, T) photon counts, 4 ps bins, ``width`` = HALF width of the square scan
                  (metres). Confocal, pre-rectified (t = 0 at the wall).
``ccsocr``        CC-SOCR / f-k "statue" (Liu et al. 2023; Lindell et al. 2019): ``sub_Sig``
                  (n, T) counts, 32 ps bins, ``C_i`` / ``C_d`` (n, 3) integer grid indices of
                  the illumination / detection points (column 0 depth, 1 horizontal, 2 vertical),
                  grid step ``wall_size_m / (grid_n - 1)``. Pre-rectified.
``general-nlos``  general-NLOS 2024 "tuan": ``data_tuan.mat`` ``counts`` (rows 0..4095 used,
                  snake scan), ``setup.mat`` ``laserpoints`` / ``detectpoints`` (64, 64, 3) in
                  metres, ``peak1.mat`` / ``peak2.mat`` wall-ranging argmax bins. Raw (legs
                  included, unknown time zero); rectified here as the authors do.

Units are converted here, at the edge (DESIGN.md section 3): the time axis becomes metres of
optical path, ``bin_width = bin_width_ps * 1e-12 * c``. For rectified data (``legs_included =
False``) the time of a confocal return from a hidden point X seen at wall point P is
t = 2 |X - P| (round trip), and for a paired scan t = |L - X| + |X - D|.

Every trace becomes one row of ``Capture.traces``; ``pairs`` holds (illuminated id, observed id).
Confocal data use one id per wall point (pairs (i, i)); the paired scan uses ids 0..n-1 for laser
points and n..2n-1 for detector points. Raw counts are kept as float64, unmodified (no
background subtraction, no zeroing of early bins: that is the estimator's job).

Neglected / assumed: the Stanford files do not say which scan index is x and which is y, nor
their sign; we take ``rect_data[i, j]`` at (x_j, y_i, 0) with x, y = linspace(-width, width, N).
The CC-SOCR files do not store the wall size or bin width; the defaults (2 m, 32 ps) are those
of CC-SOCR's ``experimental_setup.m`` for the statue and can be overridden.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..capture import Capture
from ..constants import C
from ..errors import ImportFormatError
from ..timegrid import TimeGrid

__all__ = ["read_stanford_lct", "read_ccsocr", "read_general_nlos", "detect", "FORMATS"]

FORMATS = ("stanford-lct", "ccsocr", "general-nlos")

_STANFORD_BIN_PS = 4.0
_CCSOCR_BIN_PS = 32.0
_GENERAL_BIN_PS = 32.0


# ----------------------------------------------------------------------------- helpers
def _loadmat(path: Path, fmt: str) -> dict:
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


def _field(d: dict, name: str, path: Path, fmt: str, ndim: int | None = None,
           shape: tuple | None = None) -> np.ndarray:
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


def _counts(arr: np.ndarray, name: str, path: Path, fmt: str) -> np.ndarray:
    out = arr.astype(np.float64)
    if np.any(out < 0):
        raise ImportFormatError(f"{fmt}: field '{name}' in {path} holds negative photon counts "
                                f"(min {out.min():g}); counts must be >= 0.")
    return out


# ----------------------------------------------------------------------------- Stanford LCT
def read_stanford_lct(path: str | Path, bin_width_ps: float = _STANFORD_BIN_PS) -> Capture:
    """Read an O'Toole et al. 2018 confocal scan (``rect_data`` + ``width``) into a Capture.

    Parameters
    ----------
    path : the .mat file.
    bin_width_ps : the SPAD histogram bin (4 ps in the release).

    Returns
    -------
    Capture with ``traces`` (N*N, T) raw counts, ``pairs`` (i, i), wall points in metres on
    z = 0, ``legs_included=False`` (t = 0 at the wall; a hidden point at depth r returns at
    t = 2 r metres of path).
    """
    fmt = "stanford-lct"
    path = Path(path)
    d = _loadmat(path, fmt)
    rect = _field(d, "rect_data", path, fmt, ndim=3)
    if rect.shape[0] != rect.shape[1]:
        raise ImportFormatError(f"{fmt}: field 'rect_data' in {path} must be (N, N, T) over a square "
                                f"scan grid; got {rect.shape}.")
    width = _field(d, "width", path, fmt)
    if width.size != 1 or not np.isfinite(float(width.ravel()[0])) or float(width.ravel()[0]) <= 0:
        raise ImportFormatError(f"{fmt}: field 'width' in {path} must be one positive number (the "
                                f"half width of the scan, metres); got {width.ravel()[:4]}.")
    half = float(width.ravel()[0])
    n, _, nt = rect.shape
    traces = _counts(rect, "rect_data", path, fmt).reshape(n * n, nt)
    lin = np.linspace(-half, half, n)
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    xyz = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], axis=1)
    ids = np.arange(n * n, dtype=np.int64)
    grid = TimeGrid(0.0, bin_width_ps * 1e-12 * C, nt)
    return Capture(grid=grid, traces=traces, pairs=np.stack([ids, ids], axis=1),
                   legs_included=False, illuminated_xyz=xyz, observed_xyz=xyz.copy(),
                   illuminated_ids=ids, observed_ids=ids.copy(),
                   noise={"model": "poisson"},
                   provenance={"producer": "stircasadi.acquisition.nlos_mat", "format": fmt,
                               "source_file": str(path), "bin_width_ps": float(bin_width_ps),
                               "confocal": True, "scan_shape": [int(n), int(n)],
                               "wall_half_width_m": half,
                               "note": "pre-rectified confocal: t = 2 * depth (metres of path)"})


# ----------------------------------------------------------------------------- CC-SOCR
def _ccsocr_files(path: Path) -> tuple[Path, Path, Path]:
    folder = path if path.is_dir() else path.parent
    sig = folder / "sub_Sig.mat" if path.is_dir() else path
    return sig, folder / "C_i.mat", folder / "C_d.mat"


def read_ccsocr(path: str | Path, bin_width_ps: float = _CCSOCR_BIN_PS, wall_size_m: float = 2.0,
                grid_n: int | None = None) -> Capture:
    """Read a CC-SOCR scan (``sub_Sig`` + ``C_i`` / ``C_d`` beside it) into a Capture.

    Parameters
    ----------
    path : the folder or its ``sub_Sig.mat``.
    bin_width_ps : histogram bin (32 ps for the statue).
    wall_size_m : side of the square scanned wall area (2 m for the statue).
    grid_n : points per side; default max index + 1 (64 for the statue). Step =
        wall_size_m / (grid_n - 1).

    Returns
    -------
    Capture with ``traces`` (n, T) counts; confocal (C_i == C_d) gives pairs (i, i), otherwise
    laser ids 0..n-1 and detector ids n..2n-1. ``legs_included=False``.
    """
    fmt = "ccsocr"
    path = Path(path)
    sig_p, ci_p, cd_p = _ccsocr_files(path)
    sig = _field(_loadmat(sig_p, fmt), "sub_Sig", sig_p, fmt, ndim=2)
    n, nt = sig.shape
    ci = _field(_loadmat(ci_p, fmt), "C_i", ci_p, fmt, ndim=2, shape=(n, 3))
    cd = _field(_loadmat(cd_p, fmt), "C_d", cd_p, fmt, ndim=2, shape=(n, 3))
    for name, c, p in (("C_i", ci, ci_p), ("C_d", cd, cd_p)):
        if np.any(c < 0) or np.any(c != np.round(c)):
            raise ImportFormatError(f"{fmt}: field '{name}' in {p} must hold non-negative integer grid "
                                    "indices.")
    if not (wall_size_m > 0):
        raise ImportFormatError(f"{fmt}: wall_size_m must be > 0 metres; got {wall_size_m!r}.")
    gn = int(grid_n) if grid_n is not None else int(max(ci[:, 1:].max(), cd[:, 1:].max())) + 1
    if gn < 2:
        raise ImportFormatError(f"{fmt}: the grid needs at least 2 points per side; got {gn}.")
    step = wall_size_m / (gn - 1)

    def to_xyz(c):
        c = c.astype(np.float64)
        return np.stack([c[:, 1] * step - wall_size_m / 2, c[:, 2] * step - wall_size_m / 2,
                         c[:, 0] * step], axis=1)

    traces = _counts(sig, "sub_Sig", sig_p, fmt)
    confocal = bool(np.array_equal(ci, cd))
    ill_xyz = to_xyz(ci)
    ids = np.arange(n, dtype=np.int64)
    if confocal:
        obs_xyz, obs_ids = ill_xyz.copy(), ids.copy()
    else:
        obs_xyz, obs_ids = to_xyz(cd), ids + n
    grid = TimeGrid(0.0, bin_width_ps * 1e-12 * C, nt)
    return Capture(grid=grid, traces=traces, pairs=np.stack([ids, obs_ids], axis=1),
                   legs_included=False, illuminated_xyz=ill_xyz, observed_xyz=obs_xyz,
                   illuminated_ids=ids, observed_ids=obs_ids, noise={"model": "poisson"},
                   provenance={"producer": "stircasadi.acquisition.nlos_mat", "format": fmt,
                               "source_file": str(sig_p), "bin_width_ps": float(bin_width_ps),
                               "confocal": confocal, "wall_size_m": float(wall_size_m),
                               "grid_step_m": step,
                               "note": "pre-rectified: t = |L - X| + |X - D| (confocal: 2 * depth)"})


# ----------------------------------------------------------------------------- general-NLOS
def _unsnake(counts: np.ndarray, n: int) -> np.ndarray:
    c = counts[: n * n].reshape(n, n, -1).copy()
    c[1::2] = c[1::2, ::-1]
    return c


def read_general_nlos(path: str | Path, bin_width_ps: float = _GENERAL_BIN_PS,
                      pre_bins: int = 64) -> Capture:
    """Read the general-NLOS 2024 paired scan (folder with data_tuan.mat, setup.mat, peak1/2).

    The raw histograms carry the galvo->laser-point and detector-point->galvo legs plus an
    unknown electronic delay. The wall-ranging peaks give, per pair, peak1 w = 2|L-o| + 2k and
    peak2 w = 2|D-o| + 2k, so shifting a trace left by (peak1 + peak2)/2 bins removes both legs
    and the delay exactly (the authors' rectification). We shift by the nearest integer minus
    ``pre_bins`` (kept so the early wall return stays on the grid; the grid then starts at
    ``-pre_bins * w``) and store the half-bin remainder per pair in
    ``extras['rectify_residual_m']`` (true time = grid time + residual).

    Returns
    -------
    Capture with ``traces`` (n, T') float64 counts, pairs (laser id p, detector id n + p),
    ``illuminated_xyz`` / ``observed_xyz`` from setup.mat (metres), ``legs_included=False``.
    """
    fmt = "general-nlos"
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    data_p, setup_p = folder / "data_tuan.mat", folder / "setup.mat"
    if not data_p.exists():
        cands = sorted(p.name for p in folder.glob("data_*.mat")
                       if p.name not in ("data_laser.mat", "data_detect.mat"))
        if cands:
            data_p = folder / cands[0]
    counts = _field(_loadmat(data_p, fmt), "counts", data_p, fmt, ndim=2)
    setup = _loadmat(setup_p, fmt)
    lp = _field(setup, "laserpoints", setup_p, fmt, ndim=3)
    if lp.shape[0] != lp.shape[1] or lp.shape[2] != 3:
        raise ImportFormatError(f"{fmt}: field 'laserpoints' in {setup_p} must be (n, n, 3); got {lp.shape}.")
    n = lp.shape[0]
    dp = _field(setup, "detectpoints", setup_p, fmt, ndim=3, shape=(n, n, 3))
    p1_p, p2_p = folder / "peak1.mat", folder / "peak2.mat"
    p1 = _field(_loadmat(p1_p, fmt), "peak1", p1_p, fmt, ndim=2, shape=(n, n)).astype(np.float64)
    p2 = _field(_loadmat(p2_p, fmt), "peak2", p2_p, fmt, ndim=2, shape=(n, n)).astype(np.float64)
    if counts.shape[0] < n * n:
        raise ImportFormatError(f"{fmt}: field 'counts' in {data_p} must have at least {n * n} rows "
                                f"(one per scan point); got {counts.shape}.")
    raw = _counts(_unsnake(counts, n), "counts", data_p, fmt).reshape(n * n, -1)
    nt_raw = raw.shape[1]
    mid = (p1 + p2).ravel() / 2.0
    shift = np.round(mid).astype(np.int64) - int(pre_bins)
    if np.any(mid < 0) or np.any(mid >= nt_raw):
        raise ImportFormatError(f"{fmt}: peak1/peak2 must be bin indices in [0, {nt_raw}); got range "
                                f"[{min(p1.min(), p2.min()):g}, {max(p1.max(), p2.max()):g}].")
    nt = int(nt_raw - max(shift.max(), 0))
    traces = np.zeros((n * n, nt))
    for r in range(n * n):
        s = int(shift[r])
        if s >= 0:
            traces[r] = raw[r, s:s + nt]
        else:
            traces[r, -s:] = raw[r, : nt + s]
    w = bin_width_ps * 1e-12 * C
    residual = (np.round(mid) - mid) * w  # grid time t_g = true + (mid - round(mid)) w
    ids = np.arange(n * n, dtype=np.int64)
    grid = TimeGrid(-pre_bins * w, w, nt)
    return Capture(grid=grid, traces=traces, pairs=np.stack([ids, ids + n * n], axis=1),
                   legs_included=False,
                   illuminated_xyz=lp.reshape(-1, 3).astype(np.float64),
                   observed_xyz=dp.reshape(-1, 3).astype(np.float64),
                   illuminated_ids=ids, observed_ids=ids + n * n, noise={"model": "poisson"},
                   extras={"rectify_residual_m": residual},
                   provenance={"producer": "stircasadi.acquisition.nlos_mat", "format": fmt,
                               "source_file": str(data_p), "bin_width_ps": float(bin_width_ps),
                               "confocal": False, "scan_shape": [int(n), int(n)],
                               "note": "rectified by (peak1+peak2)/2: t = |L - X| + |X - D|"})


# ----------------------------------------------------------------------------- detection
def detect(path: str | Path) -> str | None:
    """Name the format of ``path`` (a .mat file or a folder) or None when it is none of ours."""
    import scipy.io as sio

    path = Path(path)
    if path.is_dir():
        if (path / "sub_Sig.mat").exists():
            return "ccsocr"
        if (path / "setup.mat").exists() and (path / "peak1.mat").exists():
            return "general-nlos"
        mats = sorted(path.glob("*.mat"))
        for m in mats:
            got = detect(m)
            if got == "stanford-lct":
                return got
        return None
    if not path.is_file() or path.suffix.lower() != ".mat":
        return None
    try:
        names = {v[0] for v in sio.whosmat(str(path))}
    except Exception:
        return None
    if "rect_data" in names:
        return "stanford-lct"
    if "sub_Sig" in names or names & {"C_i", "C_d"}:
        return "ccsocr"
    if names & {"laserpoints", "detectpoints", "peak1", "peak2"}:
        return "general-nlos"
    if "counts" in names and (path.parent / "setup.mat").exists():
        return "general-nlos"
    return None


def read(path: str | Path, fmt: str | None = None) -> Capture:
    """Read ``path`` in format ``fmt`` (detected when None)."""
    fmt = fmt or detect(path)
    readers = {"stanford-lct": read_stanford_lct, "ccsocr": read_ccsocr,
               "general-nlos": read_general_nlos}
    if fmt not in readers:
        raise ImportFormatError(f"Cannot import {path}: format {fmt!r} is not one of {FORMATS}. "
                                "Pass --format with one of them.")
    return readers[fmt](path)
