"""``ccsocr``: CC-SOCR / f-k "statue" scans (Liu et al. 2023; Lindell et al. 2019), .mat files.

Layout: ``sub_Sig`` (n, T) counts, 32 ps bins, beside it ``C_i.mat`` / ``C_d.mat`` (n, 3) integer
grid indices of the illumination / detection points (column 0 depth, 1 horizontal, 2 vertical),
grid step ``wall_size_m / (grid_n - 1)``. Pre-rectified: t = |L - X| + |X - D| (confocal:
2 * depth), ``legs_included = False``.

Neglected / assumed: the files do not store the wall size or bin width; the defaults (2 m,
32 ps) are those of CC-SOCR's ``experimental_setup.m`` for the statue and can be overridden.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import Capture
from ...constants import C
from ...errors import ImportFormatError
from ...timegrid import TimeGrid
from .registry import Format, register
from .validate import counts, loadmat, mat_field, mat_names

NAME = "ccsocr"
BIN_PS = 32.0


def _files(path: Path) -> tuple[Path, Path, Path]:
    folder = path if path.is_dir() else path.parent
    sig = folder / "sub_Sig.mat" if path.is_dir() else path
    return sig, folder / "C_i.mat", folder / "C_d.mat"


def read_ccsocr(path: str | Path, bin_width_ps: float = BIN_PS, wall_size_m: float = 2.0,
                grid_n: int | None = None) -> Capture:
    """Read a CC-SOCR scan (``sub_Sig`` + ``C_i`` / ``C_d`` beside it) into a Capture.

    Parameters
    ----------
    path : the folder or its ``sub_Sig.mat``.
    bin_width_ps : histogram bin (32 ps for the statue).
    wall_size_m : side of the square scanned wall area (2 m for the statue).
    grid_n : points per side; default max index + 1 (64 for the statue).

    Returns
    -------
    Capture with ``traces`` (n, T) counts; confocal (C_i == C_d) gives pairs (i, i), otherwise
    laser ids 0..n-1 and detector ids n..2n-1. ``legs_included=False``.
    """
    path = Path(path)
    sig_p, ci_p, cd_p = _files(path)
    sig = mat_field(loadmat(sig_p, NAME), "sub_Sig", sig_p, NAME, ndim=2)
    n, nt = sig.shape
    ci = mat_field(loadmat(ci_p, NAME), "C_i", ci_p, NAME, ndim=2, shape=(n, 3))
    cd = mat_field(loadmat(cd_p, NAME), "C_d", cd_p, NAME, ndim=2, shape=(n, 3))
    for name, c, p in (("C_i", ci, ci_p), ("C_d", cd, cd_p)):
        if np.any(c < 0) or np.any(c != np.round(c)):
            raise ImportFormatError(f"{NAME}: field '{name}' in {p} must hold non-negative integer grid "
                                    "indices.")
    if not (wall_size_m > 0):
        raise ImportFormatError(f"{NAME}: wall_size_m must be > 0 metres; got {wall_size_m!r}.")
    gn = int(grid_n) if grid_n is not None else int(max(ci[:, 1:].max(), cd[:, 1:].max())) + 1
    if gn < 2:
        raise ImportFormatError(f"{NAME}: the grid needs at least 2 points per side; got {gn}.")
    step = wall_size_m / (gn - 1)

    def to_xyz(c):
        c = c.astype(np.float64)
        return np.stack([c[:, 1] * step - wall_size_m / 2, c[:, 2] * step - wall_size_m / 2,
                         c[:, 0] * step], axis=1)

    traces = counts(sig, "sub_Sig", sig_p, NAME)
    confocal = bool(np.array_equal(ci, cd))
    ill_xyz = to_xyz(ci)
    ids = np.arange(n, dtype=np.int64)
    obs_xyz, obs_ids = (ill_xyz.copy(), ids.copy()) if confocal else (to_xyz(cd), ids + n)
    grid = TimeGrid(0.0, bin_width_ps * 1e-12 * C, nt)
    return Capture(grid=grid, traces=traces, pairs=np.stack([ids, obs_ids], axis=1),
                   legs_included=False, illuminated_xyz=ill_xyz, observed_xyz=obs_xyz,
                   illuminated_ids=ids, observed_ids=obs_ids, noise={"model": "poisson"},
                   provenance={"producer": f"stircasadi import --format {NAME}", "format": NAME,
                               "source_format": NAME, "source_file": str(sig_p),
                               "bin_width_ps": float(bin_width_ps),
                               "confocal": confocal, "wall_size_m": float(wall_size_m),
                               "grid_step_m": step,
                               "note": "pre-rectified: t = |L - X| + |X - D| (confocal: 2 * depth)"})


def sniff(path: Path) -> bool:
    if path.is_dir():
        return (path / "sub_Sig.mat").exists()
    names = mat_names(path) if path.suffix.lower() == ".mat" else set()
    return "sub_Sig" in names or bool(names & {"C_i", "C_d"})


register(Format(NAME, "sub_Sig + C_i/C_d .mat (CC-SOCR, f-k statue)", read_ccsocr, sniff))
