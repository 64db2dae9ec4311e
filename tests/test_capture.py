"""The Capture file (DESIGN.md section 4): round trip, unknown keys kept, malformed files refused."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from stircasadi.capture import Capture, CaptureWriter
from stircasadi.errors import CaptureError
from stircasadi.timegrid import TimeGrid


def small_capture(**kw):
    rng = np.random.default_rng(0)
    base = dict(grid=TimeGrid(0.5, 0.01, 32), stir=rng.random((2, 3, 32)),
                illuminated_ids=[4, 7], observed_ids=[4, 7, 9], source_xyz=[0, 0, 0],
                irf=[0.1, 1.0, 0.1], noise={"model": "gaussian", "sigma": 0.01},
                truth={"positions": rng.random((3, 3)), "albedo": [0.1, 0.2, 0.3], "brdf": "lambertian"},
                provenance={"instrument": "test"})
    base.update(kw)
    return Capture(**base)


def test_round_trip_keeps_everything(tmp_path):
    cap = small_capture(extras={"calibration": {"__attrs__": {"t0_m": 0.12}, "gain": np.arange(3.0)},
                                "@operator": "ada"})
    path = cap.write(tmp_path / "c.h5")
    back = Capture.read(path)
    np.testing.assert_array_equal(back.stir, cap.stir)
    assert back.grid == cap.grid and back.legs_included is True
    assert back.illuminated_ids.tolist() == [4, 7] and back.observed_ids.tolist() == [4, 7, 9]
    np.testing.assert_array_equal(back.truth["albedo"], [0.1, 0.2, 0.3])
    assert back.noise["sigma"] == 0.01 and back.provenance["instrument"] == "test"
    assert back.extras["calibration"]["__attrs__"]["t0_m"] == 0.12
    np.testing.assert_array_equal(back.extras["calibration"]["gain"], np.arange(3.0))
    assert back.extras["@operator"] == "ada"
    assert back.trace(7, 9) == pytest.approx(cap.stir[1, 2])
    with pytest.raises(CaptureError, match="Unknown patch id"):
        back.trace(5, 9)


def test_file_written_by_another_tool_is_read(tmp_path):
    path = tmp_path / "ext.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "stircasadi.capture", "version": 1, "start_m": 0.0,
                        "bin_width_m": 0.004, "legs_included": False})
        f["traces"] = np.ones((4, 10))
        f["pairs"] = np.array([[0, 0], [1, 1], [2, 2], [3, 3]])
        f["observed_xyz"] = np.zeros((4, 3))
        f["my_extra"] = np.arange(5)
    cap = Capture.read(path)
    assert not cap.is_full and cap.legs_included is False
    assert cap.extras["my_extra"].tolist() == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("mutate, field", [
    (lambda f: f.attrs.__delitem__("bin_width_m"), "bin_width_m"),
    (lambda f: f.attrs.__setitem__("bin_width_m", -0.01), "bin_width"),
    (lambda f: f.attrs.__setitem__("format", "other"), "format"),
    (lambda f: f.attrs.__setitem__("version", 7), "version"),
    (lambda f: (f.__delitem__("stir"), f.__setitem__("stir", np.full((2, 3, 32), np.nan))), "NaN"),
    (lambda f: (f.__delitem__("stir"), f.__setitem__("stir", np.ones((2, 32)))), "stir"),
    (lambda f: (f.__delitem__("observed_ids"), f.__setitem__("observed_ids", [1, 2])), "observed_ids"),
    (lambda f: f.__delitem__("stir"), "stir"),
    (lambda f: (f["truth"].__delitem__("albedo"), f["truth"].__setitem__("albedo", [1.0])), "truth/albedo"),
])
def test_malformed_files_name_the_field(tmp_path, mutate, field):
    path = small_capture().write(tmp_path / "c.h5")
    with h5py.File(path, "r+") as f:
        mutate(f)
    with pytest.raises(CaptureError, match=field):
        Capture.read(path)


def test_not_hdf5_and_missing_files(tmp_path):
    bad = tmp_path / "junk.h5"
    bad.write_bytes(b"not an hdf5 file at all")
    with pytest.raises(CaptureError, match="not a readable HDF5"):
        Capture.read(bad)
    with pytest.raises(CaptureError, match="not found"):
        Capture.read(tmp_path / "missing.h5")


def test_in_memory_validation():
    g = TimeGrid(0, 0.01, 8)
    with pytest.raises(CaptureError, match="exactly one"):
        Capture(grid=g)
    with pytest.raises(CaptureError, match="time bins"):
        Capture(grid=g, stir=np.zeros((1, 1, 9)))
    with pytest.raises(CaptureError, match="pairs"):
        Capture(grid=g, traces=np.zeros((2, 8)))
    with pytest.raises(CaptureError, match="duplicate"):
        Capture(grid=g, stir=np.zeros((2, 2, 8)), observed_ids=[1, 1])


def test_failed_write_never_clobbers_existing_file(tmp_path):
    path = small_capture().write(tmp_path / "keep.h5")
    before = path.read_bytes()
    cap = small_capture()
    cap.stir[0, 0, 0] = np.nan          # becomes invalid after construction
    with pytest.raises(CaptureError):
        cap.write(path)
    assert path.read_bytes() == before


# ------------------------------------------------------------------ compressed files, one writer
def test_traces_are_compressed_one_trace_per_chunk(tmp_path):
    g = TimeGrid(0.0, 0.004, 2048)
    t = g.centres
    rate = 50 * np.exp(-0.5 * ((t - 3.0) / 0.05) ** 2)[None, None] * np.arange(1, 7).reshape(2, 3, 1)
    stir = np.random.default_rng(1).poisson(rate + 0.01).astype(float)   # SPAD counts, as measured
    path = Capture(grid=g, stir=stir).write(tmp_path / "c.h5")
    with h5py.File(path) as f:
        ds = f["stir"]
        assert ds.compression == "gzip" and ds.shuffle and ds.chunks == (1, 1, 2048)
    assert path.stat().st_size < stir.nbytes / 5          # sparse integer counts compress well
    np.testing.assert_array_equal(Capture.read(path).stir, stir)   # lossless


def test_capture_writer_rows_equal_capture_write(tmp_path):
    cap = small_capture()
    with CaptureWriter(tmp_path / "w.h5", cap.grid, 2, 3, illuminated_ids=[4, 7],
                       observed_ids=[4, 7, 9], source_xyz=[0, 0, 0], irf=cap.irf, noise=cap.noise,
                       truth=cap.truth, provenance=cap.provenance) as w:
        w.write_row(1, cap.stir[1])
        w.write_row(0, cap.stir[0])
        assert not (tmp_path / "w.h5").exists()           # nothing under the real name before commit
        w.commit()
    back = Capture.read(tmp_path / "w.h5")
    np.testing.assert_array_equal(back.stir, cap.stir)
    assert back.observed_ids.tolist() == [4, 7, 9] and back.noise["sigma"] == 0.01


def test_capture_writer_refuses_missing_rows_and_leaves_nothing(tmp_path):
    cap = small_capture()
    target = tmp_path / "w.h5"
    target.write_bytes(b"previous")
    with pytest.raises(CaptureError, match=r"rows \[1\]"):
        with CaptureWriter(target, cap.grid, 2, 3) as w:
            w.write_row(0, cap.stir[0])
            w.commit()
    assert target.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w.h5"]      # no temporary left behind


def test_failed_write_disk_full_keeps_previous_file(tmp_path):
    """A write that fails half way (file-size limit = a full disk) leaves the old file intact."""
    import subprocess
    import sys
    path = small_capture().write(tmp_path / "keep.h5")
    before = path.read_bytes()
    code = ("import resource, signal, numpy as np\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            "resource.setrlimit(resource.RLIMIT_FSIZE, (3000, 3000))\n"
            "from stircasadi.capture import Capture\nfrom stircasadi.timegrid import TimeGrid\n"
            "from stircasadi.errors import OutputError\n"
            "cap = Capture(grid=TimeGrid(0, 0.01, 4000), stir=np.random.default_rng(0).random((2, 2, 4000)))\n"
            "try:\n    cap.write(%r)\nexcept OutputError as e:\n    print('REFUSED', e)\n" % str(path))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "REFUSED" in out.stdout and "Nothing was changed" in out.stdout, out.stderr[-800:]
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.h5"]


@pytest.mark.parametrize("where", ["missing", "folder", "readonly"])
def test_unwritable_output_refused_before_work(tmp_path, where):
    from stircasadi.errors import OutputError
    cap = small_capture()
    if where == "missing":
        target = tmp_path / "nope" / "c.h5"
    elif where == "folder":
        target = tmp_path
    else:
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        target = ro / "c.h5"
    import os
    if where == "readonly" and os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    with pytest.raises(OutputError):
        cap.write(target)


# ------------------------------------------------------------------ field validation
@pytest.mark.parametrize("stir, what", [(np.ones((1, 1, 8), dtype=bool), "booleans"),
                                        (np.ones((1, 1, 8)) * (1 + 1j), "complex")])
def test_boolean_or_complex_stir_refused(stir, what):
    with pytest.raises(CaptureError, match=what):
        Capture(grid=TimeGrid(0, 0.01, 8), stir=stir)


def test_legs_included_string_refused_in_file(tmp_path):
    path = small_capture().write(tmp_path / "c.h5")
    with h5py.File(path, "r+") as f:
        f.attrs["legs_included"] = "False"
    with pytest.raises(CaptureError, match="legs_included.*boolean.*'False'"):
        Capture.read(path)


@pytest.mark.parametrize("sigma", ["0.01", -1.0, float("nan"), True])
def test_noise_sigma_must_be_a_non_negative_number(tmp_path, sigma):
    path = small_capture().write(tmp_path / "c.h5")
    with h5py.File(path, "r+") as f:
        f["noise"].attrs["sigma"] = sigma
    with pytest.raises(CaptureError, match="noise attribute 'sigma'"):
        Capture.read(path)


def test_pairs_negative_or_repeated_refused():
    g = TimeGrid(0, 0.01, 8)
    with pytest.raises(CaptureError, match="negative patch id"):
        Capture(grid=g, traces=np.zeros((2, 8)), pairs=[[0, 0], [-1, 2]])
    with pytest.raises(CaptureError, match=r"pair\(s\) \[\[1, 2\]\].*more than once"):
        Capture(grid=g, traces=np.zeros((3, 8)), pairs=[[1, 2], [0, 0], [1, 2]])


def test_single_patch_capture_is_valid(tmp_path):
    cap = Capture(grid=TimeGrid(0, 0.01, 8), stir=np.arange(8.0).reshape(1, 1, 8))
    back = Capture.read(cap.write(tmp_path / "one.h5"))
    assert back.stir.shape == (1, 1, 8) and back.trace(0, 0)[3] == 3.0
