"""Calibration against known answers: shifts, IRFs, backgrounds, Coates pile-up correction."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from acq_helpers import GRID, N_OBS, drivers
from stircasadi.acquisition.calibration import (coates, estimate_irf, first_peaks, pileup_correct,
                                                subtract_background, time_zero)
from stircasadi.acquisition.emulators import EmulatedRig
from stircasadi.capture import Capture
from stircasadi.errors import CaptureError
from stircasadi.timegrid import TimeGrid


def gauss_capture(centres, sigma_bins=2.0, background=0.0, n=200):
    k = np.arange(n)
    tr = np.stack([np.exp(-0.5 * ((k - c) / sigma_bins) ** 2) + background for c in centres])
    return Capture(grid=TimeGrid(0.0, 0.01, n), traces=tr, pairs=np.stack([np.arange(len(centres))] * 2, 1))


def test_time_zero_recovers_known_shift():
    cap = gauss_capture([50.0, 80.0, 120.0])
    centres_m = (np.array([50.0, 80.0, 120.0]) + 0.5) * 0.01
    cal = time_zero(cap, centres_m - 0.137)   # instrument is 0.137 m late
    assert cal.grid.start == pytest.approx(-0.137, abs=1e-3)
    a = cal.extras["calibration"]["__attrs__"]
    assert a["time_zero_shift_m"] == pytest.approx(0.137, abs=1e-3) and "time_zero" in a["steps"]


def test_irf_estimate_is_the_pulse():
    cap = gauss_capture([40.0, 90.0, 150.0], sigma_bins=2.0)
    irf = estimate_irf(cap, half_width=8).irf
    k = np.arange(-8, 9)
    want = np.exp(-0.5 * (k / 2.0) ** 2)
    np.testing.assert_allclose(irf, want / want.sum(), atol=1e-6)
    assert np.argmax(irf) == 8


def test_background_subtracted():
    cap = subtract_background(gauss_capture([100.0], background=0.25))
    assert np.median(cap.traces[0, :80]) == pytest.approx(0.0, abs=1e-12)
    assert cap.traces.max() == pytest.approx(1.0, abs=1e-9)


def test_coates_undoes_emulated_pileup(tmp_path):
    """High flux through the emulated TCSPC counter (first-photon histograms): Coates restores
    the true per-period photon numbers lambda."""
    t = GRID.centres
    lam = np.stack([0.02 * np.exp(-0.5 * ((t - 1.4) / 0.05) ** 2) + 1e-4] * N_OBS)  # strong pile-up
    with EmulatedRig(lambda i: lam, 1, N_OBS, GRID, detector="counter", pileup=True, seed=2,
                     sync_rate_hz=1e9) as rig, drivers(rig) as (scan, det):
        scan.aim(0)
        n_sync = 200000
        h = det.acquire(n_sync)
    raw_err = np.abs(h.sum() / n_sync - lam.sum()) / lam.sum()
    corr = coates(h, n_sync) / n_sync
    assert raw_err > 0.08                                     # pile-up loses ~12 % of photons
    assert corr.sum() == pytest.approx(lam.sum(), rel=0.01)    # corrected total within 1 %
    late = slice(33, 48)                                     # the pulse (bins after its leading edge)
    np.testing.assert_allclose(corr[:, late], lam[:, late], rtol=0.05)
    cap = Capture(grid=GRID, stir=h[None], noise={"model": "poisson", "shots": n_sync})
    assert pileup_correct(cap).stir.sum() == pytest.approx(corr.sum() * n_sync, rel=1e-9)


def test_coates_errors():
    with pytest.raises(CaptureError, match="saturated"):
        coates(np.array([[5.0, 6.0]]), 10)
    with pytest.raises(CaptureError, match="finite"):
        coates(np.array([[np.nan]]), 10)
    with pytest.raises(CaptureError, match="sync periods"):
        pileup_correct(gauss_capture([10.0]))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.integers(0, 50), min_size=1, max_size=30), st.integers(1, 2000),
       st.one_of(st.none(), st.integers(0, 5)))
def test_fuzz_coates(counts, n_sync, dead):
    try:
        out = coates(np.array([counts], float), n_sync, dead)
    except CaptureError:
        return
    assert np.all(np.isfinite(out)) and np.all(out >= np.array(counts) - 1e-9)


def test_first_peaks_subbin():
    cap = gauss_capture([60.3])
    assert first_peaks(cap.traces)[0] == pytest.approx(60.3, abs=0.05)
