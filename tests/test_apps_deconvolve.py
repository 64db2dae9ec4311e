"""apps.deconvolve / apps.sysid: the impulse STIR from coded illumination, with a stated error
measured against noise level and code length; the LTI model identified from input/output
records reproduces held-out records. Records are simulated independently of the deconvolution
(the state space driven by the code, apps.lti)."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.apps.deconvolve import (DeconvolveSettings, amcw, deconvolve, mls, pulse,
                                        simulate_records)
from stircasadi.apps.lti import drive_state_space
from stircasadi.apps.sysid import identify_fir, validate
from stircasadi.errors import CodeError
from stircasadi.problems import three_patch
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import simulate

GRID = TimeGrid(1.7, 0.01, 160)        # 1.7-3.3 m of path: the later bounces are < 1e-6 of the peak


@pytest.fixture(scope="module")
def twin():
    scene, sensor = three_patch.build_scene(), three_patch.build_sensor()
    h = simulate(scene, GRID, sensor=sensor, method="statespace", delay_mode="integer",
                 allow_truncation=True).stir
    assert h[:, :, -5:].max() < 1e-6 * h.max()     # far below the noise of every test
    return scene, sensor, h


def _driven_records(scene, sensor, code, n_ill):
    """Each illuminated patch driven alone by the code, through the state space (periodic codes:
    the second period, once the response has settled)."""
    P = code.length
    if code.periodic:
        long = TimeGrid(GRID.start, GRID.bin_width, 2 * P)
        u = np.tile(code.waveform, 3)
    else:
        long = TimeGrid(GRID.start, GRID.bin_width, GRID.n_bins + P - 1)
        u = code.waveform
    out = []
    for i in range(n_ill):
        U = np.zeros((n_ill, len(u)))
        U[i] = u
        y, _ = drive_state_space(scene, long, U, sensor)
        out.append(y[:, P:] if code.periodic else y)
    return np.array(out)[None]                      # (1 code, n_ill, n_obs, P)


@pytest.mark.parametrize("order", [8, 10])
@pytest.mark.parametrize("rel_noise", [1e-3, 1e-2])
def test_mls_twin_recovers_the_impulse_stir_within_the_stated_error(twin, order, rel_noise):
    scene, sensor, h = twin
    code = mls(order)
    clean = _driven_records(scene, sensor, code, h.shape[0])
    # the records are the code circularly convolved with the impulse STIR over one period
    # (model = physics; the STIR's later bounces, < 1e-6 of its peak, are folded in by both, and
    # light arriving more than a period late, ~1e-11 of the peak, only by the driven system)
    h_period = simulate(scene, TimeGrid(GRID.start, GRID.bin_width, code.length), sensor=sensor,
                        method="statespace", delay_mode="integer", allow_truncation=True).stir
    np.testing.assert_allclose(clean, simulate_records(h_period, [code]), rtol=0, atol=1e-10 * h.max())
    sig = rel_noise * h.max()
    y = clean + np.random.default_rng(order).normal(0.0, sig, clean.shape)
    d = deconvolve(y, [code], GRID.n_bins, bin_width=GRID.bin_width, irf=sensor.irf)
    err = np.sqrt(np.mean((d.h - h) ** 2, axis=-1))
    ratio = err / d.error_rms
    assert np.all((ratio > 0.4) & (ratio < 2.5)), ratio
    np.testing.assert_allclose(d.sigma, sig, rtol=0.25)
    # against a shorter code the error falls as 1 / sqrt(period) (multiplexing): check order 10
    if order == 10:
        d8 = deconvolve(simulate_records(h, [mls(8)], sig, np.random.default_rng(1)), [mls(8)],
                        GRID.n_bins, bin_width=GRID.bin_width, irf=sensor.irf)
        e8 = np.sqrt(np.mean((d8.h - h) ** 2))
        e10 = np.sqrt(np.mean(err ** 2))
        assert 1.3 < e8 / e10 < 3.0        # sqrt(1023 / 255) = 2.0


@pytest.mark.parametrize("codes", [[pulse(12, "hann")], [pulse(6, "rect")],
                                   amcw(range(1, 81), 256)], ids=["hann-pulse", "rect-pulse", "amcw"])
@pytest.mark.parametrize("method", ["gcv", "discrepancy"])
def test_pulses_and_amcw_recover_the_stir_with_the_stated_error(twin, codes, method):
    _, sensor, h = twin
    sig = 1e-3 * h.max()
    y = simulate_records(h, codes, sig, np.random.default_rng(5))
    d = deconvolve(y, codes, GRID.n_bins, sigma=sig if method == "discrepancy" else None,
                   bin_width=GRID.bin_width, irf=sensor.irf, settings=DeconvolveSettings(method=method))
    err = np.sqrt(np.mean((d.h - h) ** 2, axis=-1))
    big = h.max(axis=-1) > 0.01 * h.max()
    ratio = err[big] / d.error_rms[big]
    assert np.all((ratio > 0.3) & (ratio < 3.0)), ratio
    assert np.max(err) < 0.03 * h.max()


def test_ill_conditioned_codes_and_bad_records_are_refused(twin):
    _, sensor, h = twin
    kw = {"bin_width": GRID.bin_width, "irf": sensor.irf}
    with pytest.raises(CodeError, match=r"ill-conditioned.*first at DFT index 4 "):
        # a 53-bin rectangle on the 212-sample record: exact spectral zeros every 4th frequency
        deconvolve(simulate_records(h, [pulse(53)]), [pulse(53)], GRID.n_bins, **kw)
    few = amcw(range(1, 20), 256)                                                       # band to ~80
    with pytest.raises(CodeError, match=r"AMCW at every harmonic"):
        deconvolve(simulate_records(h, few), few, GRID.n_bins, **kw)
    with pytest.raises(CodeError, match=r"period \(127 bins\) is shorter than the response \(160 bins\)"):
        deconvolve(np.zeros((1, 127)), [mls(7)], GRID.n_bins, **kw)
    with pytest.raises(CodeError, match="must hold 255 samples"):
        deconvolve(np.zeros((1, 3, 200)), [mls(8)], GRID.n_bins, **kw)
    with pytest.raises(CodeError, match="cannot emit negative light"):
        from stircasadi.apps.deconvolve import Code
        Code(np.array([1.0, -1.0, 1.0]), periodic=True)
    with pytest.raises(CodeError, match="discrepancy principle needs the noise std"):
        deconvolve(simulate_records(h, [mls(8)]), [mls(8)], GRID.n_bins,
                   settings=DeconvolveSettings(method="discrepancy"), **kw)


def test_fir_identification_from_mimo_records_reproduces_held_out_records(twin):
    """Every patch driven at once by its own random binary sequence (transient, from rest): the
    identified FIR is the STIR within its stated std and predicts held-out records to the noise."""
    scene, sensor, h = twin
    rec = TimeGrid(GRID.start, GRID.bin_width, 450)
    rng = np.random.default_rng(9)

    def records(n):
        U = (rng.random((n, h.shape[0], rec.n_bins + 170)) < 0.5).astype(float)
        return U, np.array([drive_state_space(scene, rec, u, sensor)[0] for u in U])

    U, Y = records(2)
    Uv, Yv = records(2)
    sig = 1e-3 * np.abs(Y).max()
    Y = Y + rng.normal(0.0, sig, Y.shape)
    Yv = Yv + rng.normal(0.0, sig, Yv.shape)
    model = identify_fir(U, Y, GRID.n_bins)
    z = (model.h - h) / model.std
    assert 0.8 < np.sqrt(np.mean(z ** 2)) < 1.25
    np.testing.assert_allclose(model.sigma, sig, rtol=0.1)
    v = validate(model, Uv, Yv, sigma=sig)
    assert abs(v["chi2_dof"] - v["expected_chi2_dof"]) < 0.15 * v["expected_chi2_dof"], v
    with pytest.raises(CodeError, match="persistently exciting"):
        identify_fir(np.ones_like(U), Y, GRID.n_bins)
    with pytest.raises(CodeError, match="n_taps"):
        identify_fir(U, Y, 10_000)
