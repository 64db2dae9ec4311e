"""``znlos``: Zaragoza NLOS dataset HDF5 files (Galindo et al. 2019), as y-tal converts them.

Layout: ``data`` 5-D confocal ((sy, sx, bounces, t, colors) or (colors, t, bounces, sx, sy)) or
7-D exhaustive ((ly, lx, sy, sx, bounces, t, colors) or (colors, t, bounces, sx, sy, lx, ly));
colors and bounce orders are summed. ``deltaT``, ``t0`` in metres of path; the times include
both legs (``legs_included = True``). ``cameraGridPositions`` / ``laserGridPositions`` become the
observed / illuminated points, flattened in the traces' id order (confocal: both the camera
grid); ``cameraPosition`` / ``laserPosition`` the camera and source.

Neglects: the per-bounce split (summed), wall normals, the hidden-volume description.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...capture import Capture
from .registry import Format, register
from .validate import (array, check_values, fail, finite_number, grid as make_grid, h5_keys,
                       make_capture, open_h5, scalar, xyz)

NAME = "znlos"


def scan_grid(path, name, arr, scan_shape, transposed: bool) -> np.ndarray | None:
    """A Zaragoza grid (``cameraGridPositions`` / ``laserGridPositions``) as (n, 3) in the order of
    the capture's ids. The grid's scan axes come in the order of the data's scan axes in the file
    (as MATLAB wrote both; (3, A, B) or (A, B, 3)); ``transposed`` when the ids run over the
    second file axis first (as the traces are flattened)."""
    if arr is None:
        return None
    a = check_values(path, name, arr)
    A, B = scan_shape
    if a.ndim == 3 and a.shape[0] == 3 and a.shape[1:] == (A, B):
        a = np.moveaxis(a, 0, -1)
    elif a.ndim == 2 and a.shape in ((A * B, 3), (3, A * B)):
        a = (a if a.shape[1] == 3 else a.T).reshape(A, B, 3)
    elif not (a.ndim == 3 and a.shape == (A, B, 3)):
        raise fail(path, f"{name} must hold one 3-D point per scan position, shaped (3, {A}, {B}) or "
                          f"({A}, {B}, 3) like the data's scan axes; got {a.shape}.")
    if transposed:
        a = np.swapaxes(a, 0, 1)
    return a.reshape(-1, 3)


def read_znlos(path) -> Capture:
    with open_h5(path) as f:
        D = check_values(path, "data", array(path, f, "data"))
        dt = finite_number(path, "deltaT", scalar(path, f, "deltaT"))
        t0 = finite_number(path, "t0", scalar(path, f, "t0", default=0.0, required=False) or 0.0)
        cam = array(path, f, "cameraPosition", required=False)
        las = array(path, f, "laserPosition", required=False)
        cgrid = array(path, f, "cameraGridPositions", required=False)
        lgrid = array(path, f, "laserGridPositions", required=False)
    if D.ndim == 5:
        if D.shape[0] == D.shape[1]:
            H = np.moveaxis(D, [0, 1, 2, 3, 4], [3, 4, 1, 2, 0])   # (sy,sx,b,t,c) -> (c,b,t,sx,sy)
        elif D.shape[3] == D.shape[4]:
            H = np.moveaxis(D, [0, 1, 2, 3, 4], [0, 2, 1, 4, 3])   # (c,t,b,sx,sy) -> (c,b,t,sx,sy)
        else:
            raise fail(path, f"5-D 'data' must be (sy, sx, bounces, t, colors) or (colors, t, bounces, "
                              f"sx, sy) with a square scan; got shape {D.shape}.")
        first = D.shape[0] == D.shape[1]
        scan = D.shape[:2] if first else D.shape[3:]
        H = H.sum(axis=(0, 1))           # (t, sx, sy)
        nt = H.shape[0]
        traces = np.moveaxis(H, 0, -1).reshape(-1, nt)
        n = traces.shape[0]
        ids = np.arange(n)
        grid = make_grid(path, t0, dt, nt)
        # confocal: the illuminated and the observed point of trace i are the same wall point
        cg = scan_grid(path, "cameraGridPositions", cgrid, scan, transposed=not first)
        return make_capture(path, NAME, grid=grid, traces=traces, pairs=np.stack([ids, ids], 1),
                        legs_included=True, observed_xyz=cg, illuminated_xyz=cg,
                        source_xyz=None if las is None else xyz(path, "laserPosition", las, 1)[0],
                        camera_xyz=None if cam is None else xyz(path, "cameraPosition", cam, 1)[0],
                        provenance={"confocal": True,
                                    "grid_points": 0 if cg is None else int(cg.shape[0])})
    if D.ndim == 7:
        if D.shape[4] == 6:
            H = np.moveaxis(D, list(range(7)), (4, 3, 6, 5, 1, 2, 0))
        elif D.shape[2] == 6:
            H = np.moveaxis(D, list(range(7)), (0, 2, 1, 6, 5, 4, 3))
        else:
            raise fail(path, f"7-D 'data' must have its 6 bounce orders on axis 4 (ly, lx, sy, sx, "
                              f"bounces, t, colors) or axis 2 (colors, t, bounces, sx, sy, lx, ly); "
                              f"got shape {D.shape}.")
        first = D.shape[4] == 6
        lscan, cscan = (D.shape[0:2], D.shape[2:4]) if first else (D.shape[5:7], D.shape[3:5])
        H = H.sum(axis=(0, 1))           # (t, lx, ly, sx, sy)
        nt = H.shape[0]
        stir = np.moveaxis(H, 0, -1)
        stir = stir.reshape(stir.shape[0] * stir.shape[1], stir.shape[2] * stir.shape[3], nt)
        # both scan pairs are flattened second-file-axis first (see the moveaxis above)
        lg = scan_grid(path, "laserGridPositions", lgrid, lscan, transposed=True)
        cg = scan_grid(path, "cameraGridPositions", cgrid, cscan, transposed=True)
        return make_capture(path, NAME, grid=make_grid(path, t0, dt, nt), stir=stir, legs_included=True,
                        illuminated_xyz=lg, observed_xyz=cg,
                        source_xyz=None if las is None else xyz(path, "laserPosition", las, 1)[0],
                        camera_xyz=None if cam is None else xyz(path, "cameraPosition", cam, 1)[0])
    raise fail(path, f"'data' must be 5-D (confocal) or 7-D (exhaustive); got {D.ndim}-D {D.shape}.")


def sniff(path: Path) -> bool:
    if path.suffix.lower() not in (".h5", ".hdf5", ".hdf"):
        return False
    info = h5_keys(path)
    return info is not None and "data" in info[0] and "deltaT" in info[0]


register(Format(NAME, "Zaragoza NLOS HDF5 (data, deltaT, t0)", read_znlos, sniff))
