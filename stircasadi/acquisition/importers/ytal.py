"""``ytal``: y-tal's HDF5 capture files (``tal/io/capture_data.py``), read and written.

Layout: ``H`` time-first with ``H_format`` (1 T_Sx_Sy, 2 T_Lx_Ly_Sx_Sy, 3 T_Si, 4 T_Li_Si; an
HDF5 enum or int), ``delta_t`` and ``t_start`` in metres of path (``t_start`` = left edge of bin
0, our ``TimeGrid.start``), ``t_accounts_first_and_last_bounces`` -> ``legs_included``,
``sensor_grid_xyz`` / ``laser_grid_xyz`` (wall points; ``(X, Y, 3)`` or ``(N, 3)``),
``sensor_xyz`` / ``laser_xyz`` (camera and source), ``scene_info`` (YAML text).

Reading, T_Sx_Sy / T_Si (one time axis per sensor point):

* laser grid equal to the sensor grid: **confocal**, traces with pairs (k, k), both grids the
  observed and illuminated points of trace k;
* laser grid of the same size but other points: **paired** (one laser point per sensor point),
  pairs (k, n + k), laser point k illuminated id k, sensor point k observed id n + k;
* one laser point (or none): a full STIR with one illuminated row.

T_Lx_Ly_Sx_Sy and T_Li_Si give the full STIR (laser points x sensor points).

Writing (``stircasadi export CAPTURE --format ytal``): a full STIR with one illuminated row as
T_Si, with several as T_Li_Si; paired traces as T_Si with one laser and one sensor point per
trace (confocal scans on a square scan grid, from ``provenance['scan_shape']``, as T_Sx_Sy so
y-tal's f-k and LCT take them). What y-tal has no field for (patch ids, the pairs of an
irregular paired scan, the noise model) goes in ``scene_info`` under ``stircasadi`` as JSON
(valid YAML) and is restored on import, so ours -> y-tal -> ours gives the same Capture.

Neglects: wall normals (``*_grid_normals`` are not written; y-tal then takes none), y-tal's
``scene_info`` other than ours (kept as text in provenance).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ...capture import Capture
from .registry import Format, register
from .validate import (array, check_values, fail, finite_number, grid as make_grid, h5_keys,
                       make_capture, open_h5, scalar, xyz)

NAME = "ytal"
H_FORMATS = {"UNKNOWN": 0, "T_Sx_Sy": 1, "T_Lx_Ly_Sx_Sy": 2, "T_Si": 3, "T_Li_Si": 4}
GRID_FORMATS = {"UNKNOWN": 0, "N_3": 1, "X_Y_3": 2}


def _ours(info) -> dict:
    """The ``stircasadi`` part of a ``scene_info`` text (empty when absent or not ours)."""
    if not isinstance(info, str) or "stircasadi" not in info:
        return {}
    try:
        d = json.loads(info)
    except ValueError:
        return {}
    return d.get("stircasadi", {}) if isinstance(d, dict) else {}


def _restore(path, kw: dict, ours: dict) -> dict:
    """Put back what y-tal has no field for (ids, irregular pairs, noise) from ``scene_info``."""
    if not ours:
        return kw
    if "pairs" in ours and "traces" in kw:
        pairs = np.asarray(ours["pairs"], dtype=np.int64)
        if pairs.shape != (kw["traces"].shape[0], 2):
            raise fail(path, f"scene_info stircasadi.pairs has shape {pairs.shape}; the data need "
                             f"({kw['traces'].shape[0]}, 2).")
        # per-trace points -> one point per id, in the ids' order
        for col, key in ((0, "illuminated"), (1, "observed")):
            ids = np.asarray(ours.get(f"{key}_ids", np.unique(pairs[:, col])), dtype=np.int64)
            pts = kw.get(f"{key}_xyz")
            if pts is not None:
                first = {int(i): k for k, i in reversed(list(enumerate(pairs[:, col])))}
                kw[f"{key}_xyz"] = pts[[first[int(i)] for i in ids]]
            kw[f"{key}_ids"] = ids
        kw["pairs"] = pairs
    else:
        for key in ("illuminated_ids", "observed_ids"):
            if key in ours:
                kw[key] = np.asarray(ours[key], dtype=np.int64)
    if isinstance(ours.get("noise"), dict):
        kw["noise"] = ours["noise"]
    return kw


def read_ytal(path) -> Capture:
    """Read a y-tal HDF5 capture (see the module docstring for the layouts)."""
    with open_h5(path) as f:
        H = check_values(path, "H", array(path, f, "H"))
        hf = scalar(path, f, "H_format")
        try:
            hf = int(hf)
        except (TypeError, ValueError):
            raise fail(path, f"H_format must be an enum/int (1 T_Sx_Sy, 2 T_Lx_Ly_Sx_Sy, 3 T_Si, "
                             f"4 T_Li_Si); got {hf!r}.") from None
        dt = finite_number(path, "delta_t", scalar(path, f, "delta_t"))
        t0 = scalar(path, f, "t_start", default=0.0, required=False)
        t0 = 0.0 if t0 is None else finite_number(path, "t_start", t0)
        legs = scalar(path, f, "t_accounts_first_and_last_bounces", default=None, required=False)
        if legs is None:
            raise fail(path, "'t_accounts_first_and_last_bounces' is missing or empty; without it "
                             "the time origin is ambiguous. Set it in the file (True if the times "
                             "include the laser->wall and wall->sensor legs).")
        sgrid = array(path, f, "sensor_grid_xyz", required=False)
        lgrid = array(path, f, "laser_grid_xyz", required=False)
        sxyz = array(path, f, "sensor_xyz", required=False)
        lxyz = array(path, f, "laser_xyz", required=False)
        info = scalar(path, f, "scene_info", default=None, required=False)
    want_nd = {1: 3, 2: 5, 3: 2, 4: 3}
    if hf not in want_nd:
        raise fail(path, f"H_format {hf} is not supported; allowed: 1 T_Sx_Sy, 2 T_Lx_Ly_Sx_Sy, "
                         "3 T_Si, 4 T_Li_Si.")
    if H.ndim != want_nd[hf]:
        raise fail(path, f"H_format {hf} needs H with {want_nd[hf]} dimensions (time first); got "
                         f"shape {H.shape}.")
    nt = H.shape[0]
    data = np.moveaxis(H, 0, -1)  # time last
    src = xyz(path, "laser_xyz", lxyz, 1)
    cam = xyz(path, "sensor_xyz", sxyz, 1)
    ours = _ours(info)
    prov = {} if info is None or ours else {"scene_info": str(info)[:4000]}
    kw: dict = dict(grid=make_grid(path, t0, dt, nt), legs_included=bool(legs),
                    source_xyz=None if src is None else src[0], camera_xyz=None if cam is None else cam[0])
    if hf in (1, 3):
        traces = data.reshape(-1, nt)
        n = traces.shape[0]
        s = xyz(path, "sensor_grid_xyz", sgrid, n)
        lg = xyz(path, "laser_grid_xyz", lgrid)
        ids = np.arange(n)
        if lg is not None and s is not None and lg.shape == s.shape and np.allclose(lg, s):
            kw.update(traces=traces, pairs=np.stack([ids, ids], 1), observed_xyz=s, illuminated_xyz=lg)
            prov["confocal"] = True
            if hf == 1:
                prov["scan_shape"] = [int(H.shape[1]), int(H.shape[2])]
        elif lg is not None and lg.shape[0] == n and n > 1:
            kw.update(traces=traces, pairs=np.stack([ids, ids + n], 1), illuminated_xyz=lg,
                      observed_xyz=s, illuminated_ids=ids, observed_ids=ids + n)
            prov["confocal"] = False
        elif ours.get("pairs") is not None:
            kw.update(traces=traces, pairs=np.stack([ids, ids], 1))
        else:
            if lg is not None and lg.shape[0] != 1:
                raise fail(path, f"H_format {hf} with {lg.shape[0]} laser points and {n} sensor "
                                 "points is neither confocal, paired nor single-laser.")
            kw.update(stir=traces[None], observed_xyz=s, illuminated_xyz=lg)
    else:
        stir = data.reshape(data.shape[0] * data.shape[1], data.shape[2] * data.shape[3], nt) \
            if hf == 2 else data
        kw.update(stir=stir, illuminated_xyz=xyz(path, "laser_grid_xyz", lgrid, stir.shape[0]),
                  observed_xyz=xyz(path, "sensor_grid_xyz", sgrid, stir.shape[1]))
    return make_capture(path, NAME, provenance=prov, **_restore(path, kw, ours))


# ---------------------------------------------------------------------- writing
def _points(cap: Capture, which: str, ids: np.ndarray) -> np.ndarray | None:
    """The wall points of ``ids`` (None when the capture does not know them)."""
    pts = getattr(cap, f"{which}_xyz")
    if pts is None:
        return None
    known = cap.ill_ids() if which == "illuminated" else cap.obs_ids()
    row = {int(i): k for k, i in enumerate(known)}
    return pts[[row[int(i)] for i in ids]]


def write_ytal(cap: Capture, path) -> None:
    """Write ``cap`` as a y-tal HDF5 capture (see the module docstring)."""
    import h5py

    ours: dict = {"producer": "stircasadi export --format ytal",
                  "illuminated_ids": cap.ill_ids().tolist(), "observed_ids": cap.obs_ids().tolist()}
    if cap.noise:
        ours["noise"] = {k: v for k, v in cap.noise.items() if isinstance(v, (str, int, float, bool))}
    if cap.stir is not None:
        if cap.stir.shape[0] == 1:
            hf, H = "T_Si", np.moveaxis(cap.stir[0], -1, 0)
        else:
            hf, H = "T_Li_Si", np.moveaxis(cap.stir, -1, 0)
        lgrid, sgrid, gfmt = cap.illuminated_xyz, cap.observed_xyz, "N_3"
    else:
        p = cap.pairs
        lgrid, sgrid = _points(cap, "illuminated", p[:, 0]), _points(cap, "observed", p[:, 1])
        confocal = bool(np.all(p[:, 0] == p[:, 1])) and (lgrid is None or sgrid is None
                                                         or np.allclose(lgrid, sgrid))
        if confocal and lgrid is None:
            lgrid = sgrid
        if confocal and sgrid is None:
            sgrid = lgrid
        standard = (np.array_equal(p[:, 0], np.arange(len(p))) and
                    (confocal or np.array_equal(p[:, 1], np.arange(len(p)) + len(p))))
        if not standard or lgrid is None:
            ours["pairs"] = p.tolist()
        hf, H, gfmt = "T_Si", cap.traces.T, "N_3"
        shape = cap.provenance.get("scan_shape")
        if confocal and isinstance(shape, (list, tuple)) and len(shape) == 2 and \
                int(shape[0]) * int(shape[1]) == len(p) and lgrid is not None:
            a, b = int(shape[0]), int(shape[1])
            hf, H, gfmt = "T_Sx_Sy", cap.traces.T.reshape(-1, a, b), "X_Y_3"
            lgrid, sgrid = lgrid.reshape(a, b, 3), sgrid.reshape(a, b, 3)
    with h5py.File(path, "w") as f:
        f["H"] = np.ascontiguousarray(H)
        for key, value, table in (("H_format", hf, H_FORMATS),
                                  ("sensor_grid_format", gfmt if sgrid is not None else None, GRID_FORMATS),
                                  ("laser_grid_format", gfmt if lgrid is not None else None, GRID_FORMATS)):
            if value is not None:
                ds = f.create_dataset(key, (1,), dtype=h5py.enum_dtype(table, basetype="i"))
                ds[0] = table[value]
        f["delta_t"] = cap.grid.bin_width
        f["t_start"] = cap.grid.start
        f["t_accounts_first_and_last_bounces"] = bool(cap.legs_included)
        for key, value in (("sensor_grid_xyz", sgrid), ("laser_grid_xyz", lgrid),
                           ("sensor_xyz", cap.camera_xyz), ("laser_xyz", cap.source_xyz)):
            if value is not None:
                f[key] = np.asarray(value, dtype=np.float64)
        f["scene_info"] = json.dumps({"stircasadi": ours})


def sniff(path: Path) -> bool:
    if path.suffix.lower() not in (".h5", ".hdf5", ".hdf"):
        return False
    info = h5_keys(path)
    return info is not None and "H" in info[0] and "delta_t" in info[0]


register(Format(NAME, "y-tal HDF5 (H, H_format, delta_t, t_start); also written by 'export'",
                read_ytal, sniff, writer=write_ytal))
