"""``stanford-lct``: O'Toole, Lindell & Wetzstein 2018 (Nature 555, 338) confocal scans (.mat).

Layout: ``rect_data`` uint16 (N, N, T) photon counts, 4 ps bins, ``width`` = HALF width of the
square scan (metres). Confocal, pre-rectified (t = 0 at the wall): a hidden point at depth r
returns at t = 2 r metres of path, so ``legs_included = False``.

Axes: the files do not say which scan index is x and which is y, nor their sign. We take
``rect_data[i, j]`` at (x, y, 0) = (s_i, -s_j, 0) with s = linspace(-width, width, N), the hidden
scene at z > 0. Seen from the wall (looking along +z: x to the left, y up, as ``nlos.pictures``
draws maps) this is the release's own front view (``cnlos_reconstruction.m`` permutes the data to
(t, j, i), reverses i and draws j down the rows with ``imagesc``), in which the letters of the
"S", "SU" and exit-sign scans read upright; the frame is right-handed, so nothing is mirrored
(``tests/test_nlos_volumetric.py`` checks the diffuse "S" against a rasterised S).
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

NAME = "stanford-lct"
BIN_PS = 4.0


def read_stanford_lct(path: str | Path, bin_width_ps: float = BIN_PS) -> Capture:
    """Read a confocal scan (``rect_data`` + ``width``) into a Capture.

    Parameters
    ----------
    path : the .mat file (or a folder holding one).
    bin_width_ps : the SPAD histogram bin (4 ps in the release).

    Returns
    -------
    Capture with ``traces`` (N*N, T) raw counts, ``pairs`` (i, i), wall points in metres on
    z = 0, ``legs_included=False``.
    """
    path = Path(path)
    if path.is_dir():
        found = [m for m in sorted(path.glob("*.mat")) if "rect_data" in mat_names(m)]
        if not found:
            raise ImportFormatError(f"{NAME}: no .mat file with 'rect_data' in {path}.")
        path = found[0]
    d = loadmat(path, NAME)
    rect = mat_field(d, "rect_data", path, NAME, ndim=3)
    if rect.shape[0] != rect.shape[1]:
        raise ImportFormatError(f"{NAME}: field 'rect_data' in {path} must be (N, N, T) over a square "
                                f"scan grid; got {rect.shape}.")
    width = mat_field(d, "width", path, NAME)
    if width.size != 1 or not np.isfinite(float(width.ravel()[0])) or float(width.ravel()[0]) <= 0:
        raise ImportFormatError(f"{NAME}: field 'width' in {path} must be one positive number (the "
                                f"half width of the scan, metres); got {width.ravel()[:4]}.")
    half = float(width.ravel()[0])
    n, _, nt = rect.shape
    traces = counts(rect, "rect_data", path, NAME).reshape(n * n, nt)
    lin = np.linspace(-half, half, n)
    si, sj = np.meshgrid(lin, lin, indexing="ij")
    pts = np.stack([si.ravel(), -sj.ravel(), np.zeros(n * n)], axis=1)
    ids = np.arange(n * n, dtype=np.int64)
    grid = TimeGrid(0.0, bin_width_ps * 1e-12 * C, nt)
    return Capture(grid=grid, traces=traces, pairs=np.stack([ids, ids], axis=1),
                   legs_included=False, illuminated_xyz=pts, observed_xyz=pts.copy(),
                   illuminated_ids=ids, observed_ids=ids.copy(),
                   noise={"model": "poisson"},
                   provenance={"producer": f"stircasadi import --format {NAME}", "format": NAME,
                               "source_format": NAME, "source_file": str(path),
                               "bin_width_ps": float(bin_width_ps),
                               "confocal": True, "scan_shape": [int(n), int(n)],
                               "wall_half_width_m": half,
                               "note": "pre-rectified confocal: t = 2 * depth (metres of path)"})


def sniff(path: Path) -> bool:
    if path.is_dir():
        return any("rect_data" in mat_names(m) for m in sorted(path.glob("*.mat")))
    return path.suffix.lower() == ".mat" and "rect_data" in mat_names(path)


register(Format(NAME, "confocal rect_data + width .mat (O'Toole et al. 2018)", read_stanford_lct, sniff))
