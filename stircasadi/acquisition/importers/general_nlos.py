"""``general-nlos``: the general-NLOS 2024 paired scan ("tuan"): a folder of .mat files.

Layout: ``data_tuan.mat`` ``counts`` (rows 0..4095 used, snake scan), ``setup.mat``
``laserpoints`` / ``detectpoints`` (64, 64, 3) in metres, ``peak1.mat`` / ``peak2.mat``
wall-ranging argmax bins. Raw (legs included, unknown time zero); rectified here as the authors
do: the peaks give, per pair, peak1 w = 2|L-o| + 2k and peak2 w = 2|D-o| + 2k, so shifting a trace
left by (peak1 + peak2)/2 bins removes both legs and the delay; then t = |L - X| + |X - D|.

Neglects: the half-bin remainder of the integer shift is not resampled; it is stored per pair
in ``extras['rectify_residual_m']`` (true time = grid time + residual).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import Capture
from ...constants import C
from ...errors import ImportFormatError
from ...progress import progress
from ...timegrid import TimeGrid
from .registry import Format, register
from .validate import counts, loadmat, mat_field, mat_names

NAME = "general-nlos"
BIN_PS = 32.0


def _unsnake(c: np.ndarray, n: int) -> np.ndarray:
    c = c[: n * n].reshape(n, n, -1).copy()
    c[1::2] = c[1::2, ::-1]
    return c


def read_general_nlos(path: str | Path, bin_width_ps: float = BIN_PS, pre_bins: int = 64) -> Capture:
    """Read the general-NLOS paired scan (folder with data_*.mat, setup.mat, peak1/2.mat).

    ``pre_bins`` bins are kept before the rectified wall return (the grid then starts at
    ``-pre_bins * w``).

    Returns
    -------
    Capture with ``traces`` (n, T') float64 counts, pairs (laser id p, detector id n + p),
    ``illuminated_xyz`` / ``observed_xyz`` from setup.mat (metres), ``legs_included=False``.
    """
    path = Path(path)
    folder = path if path.is_dir() else path.parent
    data_p, setup_p = folder / "data_tuan.mat", folder / "setup.mat"
    if not data_p.exists():
        cands = sorted(p.name for p in folder.glob("data_*.mat")
                       if p.name not in ("data_laser.mat", "data_detect.mat"))
        if cands:
            data_p = folder / cands[0]
    raw_counts = mat_field(loadmat(data_p, NAME), "counts", data_p, NAME, ndim=2)
    setup = loadmat(setup_p, NAME)
    lp = mat_field(setup, "laserpoints", setup_p, NAME, ndim=3)
    if lp.shape[0] != lp.shape[1] or lp.shape[2] != 3:
        raise ImportFormatError(f"{NAME}: field 'laserpoints' in {setup_p} must be (n, n, 3); got {lp.shape}.")
    n = lp.shape[0]
    dp = mat_field(setup, "detectpoints", setup_p, NAME, ndim=3, shape=(n, n, 3))
    p1_p, p2_p = folder / "peak1.mat", folder / "peak2.mat"
    p1 = mat_field(loadmat(p1_p, NAME), "peak1", p1_p, NAME, ndim=2, shape=(n, n)).astype(np.float64)
    p2 = mat_field(loadmat(p2_p, NAME), "peak2", p2_p, NAME, ndim=2, shape=(n, n)).astype(np.float64)
    if raw_counts.shape[0] < n * n:
        raise ImportFormatError(f"{NAME}: field 'counts' in {data_p} must have at least {n * n} rows "
                                f"(one per scan point); got {raw_counts.shape}.")
    raw = counts(_unsnake(raw_counts, n), "counts", data_p, NAME).reshape(n * n, -1)
    nt_raw = raw.shape[1]
    mid = (p1 + p2).ravel() / 2.0
    shift = np.round(mid).astype(np.int64) - int(pre_bins)
    if np.any(mid < 0) or np.any(mid >= nt_raw):
        raise ImportFormatError(f"{NAME}: peak1/peak2 must be bin indices in [0, {nt_raw}); got range "
                                f"[{min(p1.min(), p2.min()):g}, {max(p1.max(), p2.max()):g}].")
    nt = int(nt_raw - max(shift.max(), 0))
    traces = np.zeros((n * n, nt))
    for r in progress(range(n * n), desc="rectify", unit="trace"):
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
                   provenance={"producer": f"stircasadi import --format {NAME}", "format": NAME,
                               "source_format": NAME, "source_file": str(data_p),
                               "bin_width_ps": float(bin_width_ps),
                               "confocal": False, "scan_shape": [int(n), int(n)],
                               "note": "rectified by (peak1+peak2)/2: t = |L - X| + |X - D|"})


def sniff(path: Path) -> bool:
    if path.is_dir():
        return (path / "setup.mat").exists() and (path / "peak1.mat").exists()
    if path.suffix.lower() != ".mat":
        return False
    names = mat_names(path)
    if names & {"laserpoints", "detectpoints", "peak1", "peak2"}:
        return True
    return "counts" in names and (path.parent / "setup.mat").exists()


register(Format(NAME, "raw paired counts + setup.mat + peak1/2.mat (general-NLOS 2024)",
                read_general_nlos, sniff))
