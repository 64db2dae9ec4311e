"""Importers: known answers from files written to the published layouts, and fuzzed bad input."""
from __future__ import annotations

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stircasadi.acquisition.importers import (capture_from_histograms, detect_format, import_file,
                                              phu_to_capture)
from stircasadi.constants import C
from stircasadi.errors import ImportFormatError

FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
RNG = np.random.default_rng(7)


def write_ytal(path, H, hformat, delta_t=0.01, t_start=0.5, legs=False, sensor=None, laser=None):
    with h5py.File(path, "w") as f:
        f["H"] = H
        dt = h5py.enum_dtype({"UNKNOWN": 0, "T_Sx_Sy": 1, "T_Lx_Ly_Sx_Sy": 2, "T_Si": 3, "T_Li_Si": 4},
                             basetype="i")
        ds = f.create_dataset("H_format", (1,), dtype=dt)
        ds[0] = hformat
        f["delta_t"] = delta_t
        f["t_start"] = t_start
        f["t_accounts_first_and_last_bounces"] = legs
        if sensor is not None:
            f["sensor_grid_xyz"] = sensor
        if laser is not None:
            f["laser_grid_xyz"] = laser
        f["sensor_xyz"] = np.array([0.0, 0.0, 1.0])
        f["laser_xyz"] = np.array([0.1, 0.0, 1.0])
        f["scene_info"] = "original_format: HDF5_TAL"


def test_ytal_confocal(tmp_path):
    H = RNG.random((40, 4, 5)).astype(np.float32)   # (T, Sx, Sy)
    g = np.stack(list(np.meshgrid(np.arange(4.0), np.arange(5.0), indexing="ij")) + [np.zeros((4, 5))], -1)
    p = tmp_path / "c.hdf5"
    write_ytal(p, H, 1, sensor=g, laser=g)
    assert detect_format(p) == "ytal"
    cap = import_file(p)
    assert cap.traces.shape == (20, 40) and not cap.legs_included
    assert cap.grid.start == pytest.approx(0.5) and cap.grid.bin_width == pytest.approx(0.01)
    np.testing.assert_allclose(cap.trace(7, 7), H[:, 1, 2])   # row-major Sx, Sy -> id 1*5+2
    np.testing.assert_allclose(cap.source_xyz, [0.1, 0, 1])
    # the wall grid is kept: trace 7 was measured at grid point (1, 2)
    np.testing.assert_allclose(cap.observed_xyz[7], [1.0, 2.0, 0.0])
    np.testing.assert_allclose(cap.illuminated_xyz, cap.observed_xyz)


def test_ytal_exhaustive(tmp_path):
    H = RNG.random((30, 2, 2, 3, 1))               # (T, Lx, Ly, Sx, Sy)
    p = tmp_path / "e.hdf5"
    write_ytal(p, H, 2, legs=True, sensor=RNG.random((3, 1, 3)), laser=RNG.random((2, 2, 3)))
    cap = import_file(p, "ytal")
    assert cap.stir.shape == (4, 3, 30) and cap.legs_included
    np.testing.assert_allclose(cap.stir[3, 2], H[:, 1, 1, 2, 0])


def test_znlos_confocal_sums_bounces_and_colors(tmp_path):
    D = RNG.random((4, 4, 3, 25, 2))               # (sy, sx, bounces, t, colors)
    p = tmp_path / "z.hdf5"
    with h5py.File(p, "w") as f:
        f["data"] = D
        f["deltaT"] = 0.001
        f["t0"] = 0.2
        f["cameraPosition"] = np.array([[0.0], [0.0], [1.0]])
        f["laserPosition"] = np.array([[0.1], [0.0], [1.0]])
    assert detect_format(p) == "znlos"
    cap = import_file(p)
    assert cap.legs_included and cap.traces.shape == (16, 25)
    # y-tal's conversion keeps the file's first scan axis first: id 7 = (1, 3) -> D[1, 3]
    np.testing.assert_allclose(cap.trace(7, 7), D[1, 3].sum(axis=(0, 2)))
    assert cap.grid.start == pytest.approx(0.2)


def test_csv_and_units(tmp_path):
    p = tmp_path / "t.csv"
    t_ps = 100 + 10 * np.arange(6)
    rows = "\n".join(f"{t},{k},{2 * k}" for k, t in enumerate(t_ps))
    p.write_text("time_ps,ill0_obs1,ill2_obs0\n" + rows + "\n")
    cap = import_file(p)
    assert cap.pairs.tolist() == [[0, 1], [2, 0]]
    assert cap.grid.bin_width == pytest.approx(10e-12 * C)
    assert cap.grid.start == pytest.approx(95e-12 * C)   # first sample is a bin centre
    np.testing.assert_allclose(cap.trace(2, 0), 2 * np.arange(6))


def test_npz_roundtrip(tmp_path):
    stir = RNG.random((2, 3, 10))
    p = tmp_path / "a.npz"
    np.savez(p, stir=stir, start=1.0, bin_width=0.5, time_unit="ns", legs_included=False)
    cap = import_file(p)
    np.testing.assert_array_equal(cap.stir, stir)
    assert cap.grid.bin_width == pytest.approx(0.5e-9 * C) and not cap.legs_included


def test_ptu_real_file(tmp_path):
    ptufile = pytest.importorskip("ptufile")
    data = RNG.poisson(2.0, (2, 3, 64)).astype(np.uint16)   # (Y, X, H)
    p = tmp_path / "scan.ptu"
    ptufile.imwrite(p, data, global_resolution=1e-7, tcspc_resolution=16e-12)
    cap = import_file(p)
    assert cap.traces.shape[0] == 6
    np.testing.assert_array_equal(cap.traces[:, :64], data.reshape(6, 64))
    assert cap.grid.bin_width == pytest.approx(16e-12 * C)


def test_histogram_conversion_stub():
    """STUB of ptufile's return values (PHU cannot be written with ptufile): the conversion path."""
    cap = phu_to_capture("stub.phu", [np.arange(8), np.ones(8)], [4e-12, 4e-12])
    assert cap.stir.shape == (1, 2, 8) and cap.grid.bin_width == pytest.approx(4e-12 * C)
    with pytest.raises(ImportFormatError, match="share one resolution"):
        phu_to_capture("stub.phu", [np.arange(8), np.ones(8)], [4e-12, 8e-12])
    with pytest.raises(ImportFormatError, match="negative photon"):
        capture_from_histograms("stub.ptu", [[1, -1, 2]], 4e-12, "ptu")


def test_unknown_and_missing(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"\0" * 10)
    with pytest.raises(ImportFormatError, match="ptu, phu|stanford-lct"):
        import_file(p)
    with pytest.raises(ImportFormatError, match="unknown format 'xyz'"):
        import_file(p, "xyz")
    q = tmp_path / "bad.ptu"
    q.write_bytes(b"PQTTTR\0\0garbage")
    with pytest.raises(ImportFormatError, match="PTU"):
        import_file(q)


def test_detects_real_mat_files():
    import pathlib
    d = pathlib.Path("/work/shared/data")
    if not d.exists():
        pytest.skip("shared real data not mounted")
    assert detect_format(d / "otoole2018_confocal/data_s_u.mat") == "stanford-lct"
    assert detect_format(d / "fk2019_statue_confocal/sub_Sig.mat") == "ccsocr"
    assert detect_format(d / "generalnlos2024_tuan/data_tuan.mat") == "general-nlos"


# ------------------------------------------------------------------ fuzzing
floats = st.floats(allow_nan=True, allow_infinity=True, width=32)



def _imported_data_or_refused(p):
    """Import ``p``: None when it is refused with ImportFormatError, else its traces / STIR after
    checking what every accepted file must give (finite data, positive bin width)."""
    try:
        cap = import_file(p)
    except ImportFormatError:
        return None
    data = cap.stir if cap.stir is not None else cap.traces
    assert np.all(np.isfinite(data)) and cap.grid.bin_width > 0
    return data

@FUZZ
@given(vals=st.lists(st.lists(floats, min_size=1, max_size=4), min_size=1, max_size=6),
       header=st.sampled_from(["time_ps,a", "time_zz,a", "t,a", "time_ns,ill0_obs0,ill1_obs1",
                               "nope,a", "time_s"]),
       unit=st.sampled_from([None, "ps", "furlong"]))
def test_fuzz_csv(tmp_path, vals, header, unit):
    p = tmp_path / "f.csv"
    body = "\n".join(",".join(repr(v) for v in row) for row in vals)
    p.write_text(header + "\n" + body + "\n")
    try:
        cap = import_file(p, "csv", time_unit=unit)
    except ImportFormatError:
        return
    assert np.all(np.isfinite(cap.traces))
    assert cap.traces.shape[1] == len(vals)


@FUZZ
@given(shape=st.lists(st.integers(0, 4), min_size=0, max_size=6),
       hformat=st.integers(-1, 6), delta_t=floats, t_start=floats, nan=st.booleans(),
       legs=st.sampled_from([True, False, None]))
def test_fuzz_ytal(tmp_path, shape, hformat, delta_t, t_start, nan, legs):
    p = tmp_path / "f.hdf5"
    H = np.ones(shape)
    if nan and H.size:
        H.flat[0] = np.nan
    with h5py.File(p, "w") as f:
        f["H"] = H
        f["H_format"] = hformat
        f["delta_t"] = delta_t
        f["t_start"] = t_start
        if legs is not None:
            f["t_accounts_first_and_last_bounces"] = legs
    data = _imported_data_or_refused(p)
    if data is None:
        return
    assert data.size == H.size


@FUZZ
@given(shape=st.lists(st.integers(0, 7), min_size=1, max_size=8), dt=floats, t0=floats)
def test_fuzz_znlos(tmp_path, shape, dt, t0):
    p = tmp_path / "f.hdf5"
    with h5py.File(p, "w") as f:
        f["data"] = np.ones(shape)
        f["deltaT"] = dt
        f["t0"] = t0
    _imported_data_or_refused(p)  # refused, or finite data on a positive bin width


@FUZZ
@given(arr=st.lists(floats, min_size=0, max_size=12), ndim=st.integers(1, 4),
       key=st.sampled_from(["stir", "traces", "junk"]), unit=st.sampled_from(["ps", "m", "parsec"]),
       width=floats)
def test_fuzz_npz(tmp_path, arr, ndim, key, unit, width):
    a = np.asarray(arr, dtype=float)
    a = a.reshape((1,) * (ndim - 1) + (a.size,))
    p = tmp_path / "f.npz"
    extra = {"pairs": np.zeros((a.shape[0] if a.ndim else 0, 2), int)} if key == "traces" else {}
    np.savez(p, **{key: a}, start=0.0, bin_width=width, time_unit=unit, **extra)
    _imported_data_or_refused(p)  # refused, or finite data on a positive bin width


@FUZZ
@given(blob=st.binary(min_size=0, max_size=300), prefix=st.sampled_from([b"", b"PQTTTR\0\0", b"PQHISTO\0"]),
       ext=st.sampled_from([".ptu", ".phu"]))
def test_fuzz_picoquant_garbage(tmp_path, blob, prefix, ext):
    p = tmp_path / ("f" + ext)
    p.write_bytes(prefix + blob)
    with pytest.raises(ImportFormatError):
        import_file(p)


@FUZZ
@given(hist=st.lists(st.lists(st.one_of(st.floats(-5, 1e6), st.sampled_from([np.nan, np.inf])),
                              min_size=1, max_size=5), min_size=1, max_size=3),
       res=st.one_of(floats, st.just(4e-12)))
def test_fuzz_histogram_conversion(hist, res):
    lens = {len(h) for h in hist}
    try:
        cap = capture_from_histograms("stub", hist if len(lens) == 1 else [h[:1] for h in hist], res, "ptu")
    except ImportFormatError:
        return
    assert np.all(cap.stir >= 0) and np.all(np.isfinite(cap.stir))


@pytest.mark.parametrize("layout", ["sy_sx_first", "colors_first"])
def test_znlos_confocal_grid_points_stay_with_their_traces(tmp_path, layout):
    """Each trace's wall point must be the grid point that was scanned for it: trace (a, b) of the
    file has its only return at bin 2 + 3 (a n1 + b) and grid point (a, b) is (a, b, 0.5) m. (The
    confocal readers used to drop the grid, so the wall points were unknown.)"""
    n0, n1, nt = 3, 3, 60                             # the format detection needs a square scan
    D = np.zeros((n0, n1, 6, nt, 1))                 # (sy, sx, bounces, t, colors)
    G = np.zeros((3, n0, n1))                         # MATLAB (3, A, B) order of the scan axes
    for a in range(n0):
        for b in range(n1):
            D[a, b, 1, 2 + 3 * (a * n1 + b), 0] = 1.0
            G[:, a, b] = (a, b, 0.5)
    if layout == "colors_first":
        D = np.transpose(D, (4, 3, 2, 0, 1))          # (colors, t, bounces, sx, sy)
    p = tmp_path / "z.hdf5"
    with h5py.File(p, "w") as f:
        f["data"] = D
        f["deltaT"] = 0.01
        f["cameraGridPositions"] = G
    cap = import_file(p, "znlos")
    assert cap.observed_xyz.shape == (n0 * n1, 3)
    np.testing.assert_array_equal(cap.illuminated_xyz, cap.observed_xyz)
    for i in range(n0 * n1):
        k = int(np.argmax(cap.trace(i, i)))
        a, b = cap.observed_xyz[i, :2].astype(int)
        assert k == 2 + 3 * (a * n1 + b), (i, k, a, b)


def test_znlos_exhaustive_laser_and_camera_grids_stay_with_their_traces(tmp_path):
    """Exhaustive (ly, lx, sy, sx, bounces, t, colors): trace (laser (p, q), camera (a, b)) has
    its return at bin 2 + 3 (p nq + q) + 20 (a n1 + b); the laser grid is (p, q, 0) and the camera
    grid (a, b, 1)."""
    L0, L1, n0, n1, nt = 2, 3, 2, 3, 160
    D = np.zeros((L0, L1, n0, n1, 6, nt, 1))
    for p_ in range(L0):
        for q in range(L1):
            for a in range(n0):
                for b in range(n1):
                    D[p_, q, a, b, 2, 2 + 3 * (p_ * L1 + q) + 20 * (a * n1 + b), 0] = 1.0
    LG = np.stack(list(np.meshgrid(np.arange(L0), np.arange(L1), indexing="ij")) + [np.zeros((L0, L1))])
    CG = np.stack(list(np.meshgrid(np.arange(n0), np.arange(n1), indexing="ij")) + [np.ones((n0, n1))])
    path = tmp_path / "e.hdf5"
    with h5py.File(path, "w") as f:
        f["data"] = D
        f["deltaT"] = 0.01
        f["laserGridPositions"] = LG
        f["cameraGridPositions"] = CG
    cap = import_file(path, "znlos")
    assert cap.illuminated_xyz.shape == (L0 * L1, 3) and cap.observed_xyz.shape == (n0 * n1, 3)
    for x in range(L0 * L1):
        for y in range(n0 * n1):
            p_, q = cap.illuminated_xyz[x, :2].astype(int)
            a, b = cap.observed_xyz[y, :2].astype(int)
            assert int(np.argmax(cap.stir[x, y])) == 2 + 3 * (p_ * L1 + q) + 20 * (a * n1 + b)


def test_znlos_grid_of_the_wrong_size_is_refused(tmp_path):
    p = tmp_path / "z.hdf5"
    with h5py.File(p, "w") as f:
        f["data"] = np.ones((3, 3, 6, 30, 1))
        f["deltaT"] = 0.01
        f["cameraGridPositions"] = np.zeros((3, 4, 3))
    with pytest.raises(ImportFormatError, match="cameraGridPositions"):
        import_file(p, "znlos")


# ------------------------------------------------------------------ y-tal export: ours -> y-tal -> ours
def _same_capture(a, b):
    for name in ("stir", "traces", "pairs", "illuminated_xyz", "observed_xyz", "source_xyz", "camera_xyz"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    np.testing.assert_array_equal(a.ill_ids(), b.ill_ids())
    np.testing.assert_array_equal(a.obs_ids(), b.obs_ids())
    assert a.grid == b.grid and a.legs_included == b.legs_included
    assert a.noise.get("model") == b.noise.get("model")


def _captures():
    from stircasadi.capture import Capture
    from stircasadi.timegrid import TimeGrid
    g = TimeGrid(0.25, 0.004, 40)
    rng = np.random.default_rng(3)
    wall = np.stack(list(np.meshgrid(np.linspace(-1, 1, 3), np.linspace(-1, 1, 4), indexing="ij"))
                    + [np.zeros((3, 4))], -1).reshape(12, 3)
    ids = np.arange(12)
    yield "confocal scan grid", Capture(grid=g, traces=rng.poisson(3, (12, 40)).astype(float),
                                        pairs=np.stack([ids, ids], 1), legs_included=False,
                                        illuminated_xyz=wall, observed_xyz=wall, illuminated_ids=ids,
                                        observed_ids=ids, noise={"model": "poisson"},
                                        provenance={"scan_shape": [3, 4]})
    yield "paired laser/sensor", Capture(grid=g, traces=rng.random((12, 40)), pairs=np.stack([ids, ids + 12], 1),
                                         legs_included=False, illuminated_xyz=wall, observed_xyz=wall + 0.1,
                                         illuminated_ids=ids, observed_ids=ids + 12)
    yield "irregular pairs, no points", Capture(grid=g, traces=rng.random((3, 40)),
                                                pairs=[[5, 9], [2, 9], [5, 1]])
    yield "full STIR with ids", Capture(grid=g, stir=rng.random((2, 3, 40)), illuminated_ids=[4, 7],
                                        observed_ids=[4, 7, 9], source_xyz=[0, 0, 1], camera_xyz=[0.1, 0, 1],
                                        illuminated_xyz=wall[:2], observed_xyz=wall[2:5],
                                        noise={"model": "gaussian", "sigma": 0.01})
    yield "one laser point", Capture(grid=g, stir=rng.random((1, 5, 40)), observed_xyz=wall[:5],
                                     illuminated_xyz=wall[5:6])


@pytest.mark.parametrize("name, cap", list(_captures()), ids=[n for n, _ in _captures()])
def test_ytal_export_round_trip(tmp_path, name, cap):
    from stircasadi.acquisition.importers import export_file
    y = export_file(cap, "ytal", tmp_path / "y.hdf5")
    assert detect_format(y) == "ytal"
    _same_capture(import_file(y), cap)


def test_ytal_export_of_a_confocal_grid_is_t_sx_sy(tmp_path):
    """A confocal scan on a square grid is written the way y-tal's own files are (T_Sx_Sy)."""
    from stircasadi.acquisition.importers import export_file
    cap = dict(_captures())["confocal scan grid"]
    y = export_file(cap, "ytal", tmp_path / "y.hdf5")
    with h5py.File(y) as f:
        assert f["H"].shape == (40, 3, 4) and int(f["H_format"][0]) == 1
        assert f["sensor_grid_xyz"].shape == (3, 4, 3) and not f["t_accounts_first_and_last_bounces"][()]
        np.testing.assert_array_equal(f["H"][:, 1, 2], cap.traces[6])


def test_ytal_own_reader_opens_our_export(tmp_path):
    """y-tal's NLOSCaptureData reads the export (y-tal is not a dependency: skipped without it)."""
    tal = pytest.importorskip("tal")
    from stircasadi.acquisition.importers import export_file
    for name, cap in _captures():
        y = export_file(cap, "ytal", tmp_path / f"{abs(hash(name))}.hdf5")
        data = tal.io.read_capture(str(y))
        H = cap.traces.T if cap.traces is not None else np.moveaxis(cap.stir, -1, 0)
        np.testing.assert_array_equal(np.asarray(data.H).reshape(H.shape), H)
        assert data.delta_t == pytest.approx(cap.grid.bin_width)
