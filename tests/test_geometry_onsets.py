"""Onsets: sub-bin accuracy, honest uncertainty, CRB, Poisson + background (twin experiments)."""
import numpy as np
import pytest

from stircasadi.geometry import onsets as on
from stircasadi.timegrid import TimeGrid

GRID = TimeGrid(0.0, 0.005, 400)
TMPL = on.GaussTemplate(0.0267, 0.005)  # the default 210 ps FWHM IRF on 5 mm bins
C = GRID.start + (np.arange(GRID.n_bins) + 0.5) * GRID.bin_width


def _pulse(tau, amp=1.0, bg=0.0):
    g, _ = TMPL.pulse(C - tau)
    return amp * g + bg


def test_clean_pulse_is_recovered_below_the_bin():
    for tau in (1.0, 1.0012, 1.0031, 0.9977):
        f = on.fit_onsets(_pulse(tau, 2.0, 0.3)[None], GRID, TMPL, np.array([tau + 0.004]))
        assert abs(f.tau[0] - tau) < 1e-9


@pytest.mark.parametrize("sigma", [2e-3, 1e-2])
def test_gaussian_noise_spread_matches_stated_std_and_crb(sigma):
    rng = np.random.default_rng(7)
    tau, amp = 1.00123, 10.0
    Y = _pulse(tau, amp, 0.05)[None] + rng.normal(0, sigma, (400, GRID.n_bins))
    f = on.fit_onsets(Y, GRID, TMPL, np.full(400, tau), right_sigmas=4.0)
    err = f.tau - tau
    assert abs(err.mean()) < 4 * err.std() / np.sqrt(400)
    ratio = err.std() / np.median(f.tau_std)
    assert 0.85 < ratio < 1.2
    crb = on.onset_crb(TMPL, amp, sigma, GRID, tau)
    assert err.std() < 1.2 * crb


def test_poisson_with_background():
    rng = np.random.default_rng(3)
    tau = 1.2017
    lam = _pulse(tau, 400.0, 5.0)
    Y = rng.poisson(np.tile(lam, (300, 1))).astype(float)
    f = on.fit_onsets(Y, GRID, TMPL, np.full(300, tau), poisson=True, right_sigmas=4.0)
    err = f.tau - tau
    assert abs(err.mean()) < 4 * err.std() / np.sqrt(300)
    assert 0.8 < err.std() / np.median(f.tau_std) < 1.25
    assert np.all(np.abs(f.background - 5.0) < 3.0)


def test_detect_pulses_finds_two_separated_families_in_order():
    rng = np.random.default_rng(1)
    y = _pulse(0.8, 5.0) + _pulse(1.3, 2.0) + rng.normal(0, 1e-3, GRID.n_bins)
    p = on.detect_pulses(y, GRID, TMPL, max_pulses=3)
    assert len(p) == 2
    assert abs(p[0]["tau"] - 0.8) < 5e-4 and abs(p[1]["tau"] - 1.3) < 5e-4


def test_sampled_template_matches_gaussian():
    """A measured response (ArrayIRF from Gaussian samples) gives the same template as the
    Gaussian it samples: one bin integral for both."""
    from stircasadi.irf import ArrayIRF, Template
    g, _ = TMPL.pulse(np.arange(-20, 21) * 0.005)
    s = Template(ArrayIRF(tuple(g), 0.005), 0.005)
    x = np.linspace(-0.05, 0.05, 41)
    assert np.max(np.abs(s.pulse(x)[0] - TMPL.pulse(x)[0])) < 2e-3 * g.max()


@pytest.mark.parametrize("tau0", [0.0, 0.01, 0.02])
def test_window_clipped_at_grid_start_gives_no_infinite_snr(tau0):
    """A fit window clipped at the start of the grid used to end with a near-exact fit of <= 3
    bins whose cost and curvature belonged to an earlier window: zero std and SNR ~1e302 on pure
    noise (seen as 4 bogus 'second onsets' before t = 0 in Fig. 13). Every accepted fit of noise
    now has a positive std, an SNR of noise size, and a peak inside the data."""
    rng = np.random.default_rng(3)
    Y = rng.normal(0.0, 1.0, (500, GRID.n_bins))
    f = on.fit_onsets(Y, GRID, TMPL, np.full(500, tau0))
    assert np.all(f.tau_std[f.found] > 0)
    assert np.all(f.tau[f.found] >= GRID.start)
    assert f.snr[f.found].max() < 30.0


def _detect_pulses_loop(y, grid, tmpl, max_pulses=1, k_sigma=6.0, t_min=None, poisson=False,
                        rel_min=0.0, model="pulse", right_sigmas=1.5):
    """The former per-trace ``detect_pulses`` (one trace, Python loop over passes; failed fits
    skipped as the package now does): reference for the batched one."""
    import math
    y = np.asarray(y, float)
    w = grid.bin_width
    c = grid.start + (np.arange(len(y)) + 0.5) * w
    sig = float(on.noise_level(y))
    bg = float(np.median(y[: max(8, len(y) // 8)])) if t_min is None else \
        float(np.median(y[c < t_min])) if np.any(c < t_min) else float(np.median(y))
    resid = y.copy()
    out = []
    tlo = -np.inf if t_min is None else t_min
    W = tmpl.width
    half = int(math.ceil(2.5 * tmpl.width / w))
    k, _ = tmpl.pulse(np.arange(-half, half + 1) * w)
    k = k / k.sum()
    sm_noise = sig * math.sqrt(float(np.sum(k * k)))
    first_amp = None
    for _ in range(max_pulses):
        sm = on._smooth(resid, tmpl, w)
        if poisson:
            thr = bg + k_sigma * np.sqrt(np.maximum(sm, 1.0)) * (sm_noise / max(sig, 1e-300) if sig > 0 else 1)
        else:
            thr = bg + k_sigma * max(sm_noise, 1e-300)
        above = np.flatnonzero((sm > thr) & (c >= tlo))
        if above.size == 0:
            break
        kp = int(on._first_peak(sm[None], np.array([int(above[0])]), int(math.ceil(8 * W / w)))[0]) \
            if model == "pulse" else int(above[0])
        tau0 = c[kp]
        fit = on.fit_onsets(resid[None], grid, tmpl, np.array([tau0]), model=model, poisson=poisson,
                            right_sigmas=right_sigmas, background=None)
        if not fit.found[0]:  # a diverged fit: skipped, the search goes on after the crossing
            tlo = tau0 + 0.5 * W
            continue
        tau = float(fit.tau[0])
        amp = float(fit.amplitude[0])
        if first_amp is None:
            first_amp = amp
        elif amp < rel_min * first_amp:
            break
        out.append({"tau": tau, "tau_std": float(fit.tau_std[0]), "amplitude": amp,
                    "snr": float(fit.snr[0])})
        g, _ = tmpl.pulse(c - tau)
        resid = resid - amp * g
        tlo = tau + 0.5 * W
    return out


def _multi_family_traces(n, seed, poisson=False):
    """n seeded traces with 1-4 families each (some overlapping), random amplitudes and noise."""
    rng = np.random.default_rng(seed)
    Y = np.zeros((n, GRID.n_bins))
    for k in range(n):
        nf = rng.integers(1, 5)
        taus = np.sort(rng.uniform(0.3, 1.8, nf))
        for t in taus:
            Y[k] += _pulse(t, rng.uniform(0.2, 5.0))
    if poisson:
        return rng.poisson(200.0 * Y + 3.0).astype(float)
    return Y + rng.normal(0, 1, Y.shape) * 10 ** rng.uniform(-3, -0.5, (n, 1))


def test_fit_onsets_rows_are_independent():
    """Each row is fitted as if alone (own convergence, own window updates): the batch equals the
    row-by-row fits exactly (formerly the whole batch iterated until its slowest row converged)."""
    Y = _multi_family_traces(120, 11)
    rng = np.random.default_rng(2)
    tau0 = rng.uniform(0.3, 1.8, 120)
    f = on.fit_onsets(Y, GRID, TMPL, tau0)
    for k in range(0, 120, 7):
        g = on.fit_onsets(Y[k:k + 1], GRID, TMPL, tau0[k:k + 1])
        assert g.found[0] == f.found[k]
        for name in ("tau", "tau_std", "amplitude", "snr"):
            a, b = getattr(f, name)[k], getattr(g, name)[0]
            assert a == b or np.isnan(a) and np.isnan(b), (k, name)


@pytest.mark.parametrize("poisson", [False, True])
def test_batched_detection_equals_per_trace_loop(poisson):
    """detect_pulses_batch on 80 multi-family traces = the former per-trace loop, trace by trace
    (the same floating-point operations per row, so equal, not just close)."""
    Y = _multi_family_traces(80, 5, poisson)
    kw = dict(max_pulses=5, poisson=poisson, rel_min=0.02 if poisson else 0.0)
    new = on.detect_pulses_batch(Y, GRID, TMPL, **kw)
    n_fam = 0
    for y, pn in zip(Y, new):
        po = _detect_pulses_loop(y, GRID, TMPL, **kw)
        assert pn == po
        n_fam += len(po)
    assert n_fam > 150  # multi-family traces really were tested
    assert new[3] == on.detect_pulses(Y[3], GRID, TMPL, **kw)
