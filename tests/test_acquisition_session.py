"""Capture sessions over emulated rigs: files equal the source, faults lose nothing, resume completes."""
from __future__ import annotations

import h5py
import numpy as np
import pytest

from acq_helpers import GRID, N_OBS, N_PATCH, drivers, synthetic_row
from stircasadi.acquisition.emulators import EmulatedRig, Fault
from stircasadi.acquisition.journal import journal_path
from stircasadi.acquisition.session import acquire, read_partial
from stircasadi.capture import Capture
from stircasadi.errors import CaptureError, InstrumentError

GAIN, SHOTS = 0.5, 4000
TRUTH = np.stack([synthetic_row(i) for i in range(N_PATCH)])


def counter_rig(**kw):
    return EmulatedRig(synthetic_row, N_PATCH, N_OBS, GRID, detector="counter", seed=11, gain=GAIN,
                       sync_rate_hz=1e8, **kw)


def test_complete_capture_matches_source(tmp_path):
    out = tmp_path / "cap.h5"
    seen = []
    with counter_rig() as rig, drivers(rig) as (scan, det):
        acquire(scan, det, out, shots=SHOTS, progress=lambda d, t, p, e: seen.append((d, t, p)))
    assert seen == [(1, 3, 0), (2, 3, 1), (3, 3, 2)]
    assert not journal_path(out).exists()
    cap = Capture.read(out)
    assert cap.stir.shape == (N_PATCH, N_OBS, GRID.n_bins)
    expect = SHOTS * GAIN * TRUTH
    z = (cap.stir - expect) / np.sqrt(expect + 1)
    assert np.max(np.abs(z)) < 6
    assert cap.grid.bin_width == pytest.approx(GRID.bin_width)
    assert cap.provenance["instrument"].startswith("PICOEMU,HISTO-8")
    assert cap.noise["model"] == "poisson" and cap.noise["shots"] == SHOTS
    assert cap.extras["acquisition"]["acquired"].all()


@pytest.mark.parametrize("kind", ["tektronix", "lecroy"])
def test_scope_capture_is_average_of_shots(tmp_path, kind):
    out = tmp_path / "scope.h5"
    with EmulatedRig(synthetic_row, N_PATCH, N_OBS, GRID, detector=kind, seed=5, volts_per_unit=0.1,
                     noise_v=0.02) as rig, drivers(rig) as (scan, det):
        acquire(scan, det, out, shots=16)
    cap = Capture.read(out)
    resid = cap.stir - 0.1 * TRUTH
    # averaging 16 shots: noise sigma 0.02/4 = 0.005 V
    assert np.std(resid) == pytest.approx(0.005, rel=0.15)
    assert cap.noise["model"] == "gaussian"


# each fault: (device, fault, command that must be named in the error)
FAULTS = [
    ("detector", Fault("stall", "HIST?", nth=3, stall_s=0.8), "HIST? 0"),
    ("detector", Fault("drop", "HIST?", nth=3, n_bytes=40), "HIST? 0"),
    ("detector", Fault("garbage", "HIST?", nth=3, n_bytes=5), "HIST? 0"),
    ("detector", Fault("truncate", "HIST?", nth=3), "HIST? 0"),
    ("detector", Fault("disconnect", "ACQ", nth=2), "ACQ 4000"),
    ("scan", Fault("garbage", "AIM", nth=2, n_bytes=4), "AIM 1"),
    ("scan", Fault("stall", "AIM", nth=2, stall_s=0.8), "AIM 1"),
    ("scan", Fault("disconnect", "AIM", nth=2), "AIM 1"),
]


@pytest.mark.parametrize("where,fault,command", FAULTS, ids=[f"{w}-{f.kind}-{f.command}" for w, f, _ in FAULTS])
def test_fault_raises_keeps_traces_and_resumes(tmp_path, where, fault, command):
    out = tmp_path / "cap.h5"
    kw = {"scan_faults": [fault]} if where == "scan" else {"detector_faults": [fault]}
    with counter_rig(**kw) as rig:
        with drivers(rig, retries=0) as (scan, det):
            with pytest.raises(InstrumentError) as ei:
                acquire(scan, det, out, shots=SHOTS)
        msg = str(ei.value)
        device = "scan controller" if where == "scan" else "counter"
        assert device in msg and repr(command) in msg and "received" in msg
        assert "--resume" in msg
        # patch 0 (and only the completed patches) are on disk, exactly as measured
        part = read_partial(journal_path(out))
        assert 0 in part.pairs[:, 0]
        done_before = set(part.pairs[:, 0].tolist())
        assert 2 not in done_before
        saved = {int(i): part.trace(int(i), 0).copy() for i in done_before}
        assert not out.exists()
        # re-plug and resume
        rig.reconnect()
        with drivers(rig) as (scan, det):
            acquire(scan, det, out, shots=SHOTS, resume=True)
    cap = Capture.read(out)
    for i, tr in saved.items():
        np.testing.assert_array_equal(cap.stir[i, 0], tr)  # nothing measured was lost or redone
    expect = SHOTS * GAIN * TRUTH
    assert np.max(np.abs((cap.stir - expect) / np.sqrt(expect + 1))) < 6
    with h5py.File(out) as f:
        assert f["acquisition/acquired"][()].all()
        assert "done_before" in f["provenance"].attrs["resumed"]


@pytest.mark.parametrize("kind", ["stall", "garbage", "truncate", "drop"])
def test_transient_fault_recovered_by_retry(tmp_path, kind):
    out = tmp_path / "cap.h5"
    fault = Fault(kind, "HIST?", nth=2, stall_s=0.5, n_bytes=6)
    with counter_rig(detector_faults=[fault]) as rig, drivers(rig, retries=2) as (scan, det):
        acquire(scan, det, out, shots=SHOTS)
        assert det.port.retries_used >= 1
    cap = Capture.read(out)
    assert cap.provenance["retries"] >= 1
    expect = SHOTS * GAIN * TRUTH
    assert np.max(np.abs((cap.stir - expect) / np.sqrt(expect + 1))) < 6


def test_refuses_to_overwrite_and_resume_mismatch(tmp_path):
    out = tmp_path / "cap.h5"
    with counter_rig(detector_faults=[Fault("disconnect", "ACQ", nth=2)]) as rig:
        with drivers(rig) as (scan, det):
            with pytest.raises(InstrumentError):
                acquire(scan, det, out, shots=SHOTS)
        rig.reconnect()
        with drivers(rig) as (scan, det):
            with pytest.raises(CaptureError, match="--resume"):
                acquire(scan, det, out, shots=SHOTS)
            with pytest.raises(CaptureError, match="shots 4000 != requested 10"):
                acquire(scan, det, out, shots=10, resume=True)
            acquire(scan, det, out, shots=SHOTS, resume=True)
            with pytest.raises(CaptureError, match="already exists"):
                acquire(scan, det, out, shots=SHOTS)
