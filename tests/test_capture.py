"""The Capture file (DESIGN.md section 4): round trip, unknown keys kept, malformed files refused."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from stircasadi.capture import Capture
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
