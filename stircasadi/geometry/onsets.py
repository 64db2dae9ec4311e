"""Onsets: the path length of the earliest path of a bounce family, below the bin width.

When to use: first step of the geometry stage, on any Capture (simulated or measured).

Model fitted (per trace, on a window around the family's leading edge)::

    pulse:  y_k = a * g(c_k - tau) + b        (a point-like family: one IRF centred on tau)
    edge:   y_k = a * G(c_k - tau) + b        (an extended surface: a step blurred by the IRF)

c_k is bin k's centre, g the bin-integrated impulse response for a path at offset x from a bin
centre (``stircasadi.irf.Template``: the same bin integral as the forward model, for a Gaussian
or a measured response), G its running integral (per bin) and b a constant background.
tau is the onset (the IRF is centred on the path length, sensor.py). Fitting is a batched
Levenberg-Marquardt over all traces at once. Weights: Gaussian noise -> uniform, noise sigma
from the fit residual; Poisson counts -> 1/max(model, 1) (iteratively reweighted).

Uncertainty: tau_std = sqrt([(J^T W J)^-1]_tau,tau) (times the residual scale for Gaussian
noise). This is the Cramer-Rao bound of the window model evaluated at the estimate; the
benchmark (benchmarks/geometry.py) compares the empirical spread with the CRB of the full trace.

Neglects: later families that start inside the fit window bias tau (the window stops
``right_sigmas`` IRF widths after the peak to limit this); an ideal (no) IRF gives no sub-bin
information (tau = bin centre, std = w / sqrt(12)).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..irf import GaussianIRF, IdealIRF, Template, estimate_samples, from_samples

__all__ = ["GaussTemplate", "make_template", "estimate_irf", "fit_onsets", "detect_pulses",
           "detect_pulses_batch",
           "trace_onsets", "first_onsets", "second_onsets", "third_onsets", "noise_level",
           "OnsetFit", "onset_crb"]

_CHUNK_SAMPLES = 1 << 22  # traces x bins handled at once by the STIR-level functions


# ----------------------------------------------------------------------------- templates
def GaussTemplate(sigma: float, w: float) -> Template:
    """The onset template of a Gaussian response of std ``sigma`` on bins of width ``w``."""
    return Template(GaussianIRF.from_sigma(sigma), w)


def make_template(capture=None, irf: np.ndarray | None = None, bin_width: float | None = None,
                  fwhm: float | None = None) -> Template | None:
    """The onset template: from ``fwhm`` (Gaussian, metres of path), ``irf`` samples, the
    capture's ``irf``, or estimated from the capture's first-bounce returns
    (``stircasadi.irf.from_samples`` decides Gaussian or measured, as for the model). Returns
    None for an ideal (one-bin) response."""
    w = bin_width if bin_width is not None else capture.grid.bin_width
    if fwhm is not None:
        return Template(GaussianIRF(fwhm), w)
    if irf is None and capture is not None:
        irf = capture.irf
    if irf is None and capture is not None:
        irf = estimate_irf(capture)
    if irf is None:
        return None
    resp = from_samples(irf, w)
    return None if isinstance(resp, IdealIRF) else Template(resp, w)


def estimate_irf(capture, half_bins: int = 40) -> np.ndarray | None:
    """The impulse response from the first-bounce returns of a full STIR's diagonal traces
    (``stircasadi.irf.estimate_samples``); None when unusable."""
    if capture.stir is None:
        return None
    common = np.intersect1d(capture.ill_ids(), capture.obs_ids())
    if common.size == 0:
        return None
    return estimate_samples(np.stack([capture.trace(i, i) for i in common]), half_bins=half_bins)


# ----------------------------------------------------------------------------- noise
def noise_level(y: np.ndarray) -> np.ndarray:
    """Robust per-trace noise std from first differences (MAD / 0.6745 / sqrt 2)."""
    d = np.diff(y, axis=-1)
    med = np.median(d, axis=-1, keepdims=True)
    return np.median(np.abs(d - med), axis=-1) / 0.6745 / math.sqrt(2.0)


# ----------------------------------------------------------------------------- batched fit
@dataclass
class OnsetFit:
    """Result arrays of ``fit_onsets`` (one entry per trace)."""

    tau: np.ndarray
    tau_std: np.ndarray
    amplitude: np.ndarray
    background: np.ndarray
    snr: np.ndarray
    found: np.ndarray
    chi2: np.ndarray


def _normal_eq(g, dg, a, w, r, npar):
    """J^T W J (n, npar, npar) and J^T W r (n, npar) for J = [g, -a dg, 1][:npar]."""
    J = np.stack([g, -a * dg, np.ones_like(g)][:npar], axis=2)
    return np.einsum("nlp,nl,nlq->npq", J, w, J), np.einsum("nlp,nl,nl->np", J, w, r)


def _solve_rows(A, b):
    """Batched solve of A x = b, rows whose A is singular get a zero step (as a lone row would)."""
    try:
        return np.linalg.solve(A, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.zeros_like(b)
        for k in range(A.shape[0]):
            try:
                out[k] = np.linalg.solve(A[k], b[k])
            except np.linalg.LinAlgError:
                pass
        return out


def _lm(y, c, p, tmpl, model, poisson, n_iter=40, fix_b=False, mask=None):
    """Batched Levenberg-Marquardt on y (n, L) with bin centres c (n, L); p = (n, 3) [a, tau, b].

    Each row stops on its own (onset step < 1e-6 bin after at least 5 iterations) and is then
    dropped from the batch, so a row's result does not depend on the other rows it is fitted with."""
    f = tmpl.pulse if model == "pulse" else tmpl.edge
    n = y.shape[0]
    npar = 2 if fix_b else 3
    p = p.copy()

    def resid(p, y, c, mask):
        g, dg = f(c - p[:, 1:2])
        m = p[:, 0:1] * g + p[:, 2:3]
        w = 1.0 / np.maximum(m, 1.0) if poisson else np.ones_like(m)
        if mask is not None:
            w = w * mask
        return y - m, g, dg, w

    r, g, dg, w = resid(p, y, c, mask)
    cost = np.sum(w * r * r, axis=1)
    # working copies of the rows still iterating (compacted as rows stop)
    act = np.arange(n)
    ya, ca, ma = y, c, mask
    pa, ra, ga, dga, wa, costa = p.copy(), r, g, dg, w, cost.copy()
    lam = np.full(n, 1e-3)
    eye = np.eye(npar)[None]
    for it in range(n_iter):
        JTJ, JTr = _normal_eq(ga, dga, pa[:, 0:1], wa, ra, npar)
        diag = np.einsum("npp->np", JTJ)
        A = JTJ + lam[:, None, None] * eye * (diag[:, :, None] + 1e-30)
        step = _solve_rows(A, JTr)
        # cap the onset step at one IRF width
        step[:, 1] = np.clip(step[:, 1], -tmpl.width, tmpl.width)
        pn = pa.copy()
        pn[:, :npar] += step
        rn, gn, dgn, wn = resid(pn, ya, ca, ma)
        costn = np.sum(wn * rn * rn, axis=1)
        ok = np.isfinite(costn) & (costn <= costa)
        pa[ok] = pn[ok]
        ra[ok], ga[ok], dga[ok], wa[ok], costa[ok] = rn[ok], gn[ok], dgn[ok], wn[ok], costn[ok]
        lam = np.where(ok, lam * 0.3, lam * 10.0)
        done = (np.abs(step[:, 1]) < 1e-6 * tmpl.w) if it > 3 else np.zeros(len(act), bool)
        if done.any() or it == n_iter - 1:
            fin = done if it < n_iter - 1 else np.ones(len(act), bool)
            ia = act[fin]
            p[ia], r[ia], g[ia], dg[ia], w[ia], cost[ia] = pa[fin], ra[fin], ga[fin], dga[fin], wa[fin], costa[fin]
            keep = ~fin
            if not keep.any():
                break
            act = act[keep]
            ya, ca = ya[keep], ca[keep]
            ma = ma[keep] if ma is not None else None
            pa, ra, ga, dga, wa, costa, lam = (pa[keep], ra[keep], ga[keep], dga[keep], wa[keep],
                                               costa[keep], lam[keep])
    JTJ, _ = _normal_eq(g, dg, p[:, 0:1], w, r, npar)
    return p, JTJ, cost


def fit_onsets(y: np.ndarray, grid, tmpl, tau0: np.ndarray, model: str = "pulse",
               poisson: bool = False, right_sigmas: float = 1.5, left_sigmas: float = 4.0,
               sigma_noise: np.ndarray | None = None, background: np.ndarray | None = None) -> OnsetFit:
    """Fit the onset of the family near ``tau0`` in each row of ``y`` (n, n_bins).

    The window is [tau0 - left_sigmas*W, peak + right_sigmas*W] (W = IRF width); for
    ``model="edge"`` it ends at the plateau instead. Returns an ``OnsetFit``.
    """
    y = np.atleast_2d(np.asarray(y, float))
    n, nb = y.shape
    w = grid.bin_width
    tau0 = np.broadcast_to(np.asarray(tau0, float), (n,)).copy()
    W = tmpl.width
    # at least a few bins on each side: a response narrower than a bin is still fitted
    nl = max(int(math.ceil(left_sigmas * W / w)) + 1, 4)
    nr = max(int(math.ceil((right_sigmas + 1.5) * W / w)) + 1, 6)
    L = nl + nr + 1
    k0 = np.round((tau0 - grid.start) / w - 0.5).astype(int)
    starts = np.clip(k0 - nl, 0, max(nb - L, 0))
    L = min(L, nb)
    idx = starts[:, None] + np.arange(L)[None, :]
    Y = np.take_along_axis(y, idx, axis=1)
    C = grid.start + (idx + 0.5) * w
    if background is None:
        b0 = np.median(Y[:, : max(3, nl // 2)], axis=1)
    else:
        b0 = np.asarray(background, float) * np.ones(n)
    if model == "pulse":
        a0 = np.maximum(Y.max(axis=1) - b0, 1e-30)
        g0, _ = tmpl.pulse(np.zeros(1))
        a0 = a0 / max(float(g0[0]), 1e-12)
    else:
        a0 = np.maximum(np.percentile(Y, 90, axis=1) - b0, 1e-30)
    # Restrict the window's right end: for a pulse stop right_sigmas*W after tau0; edges need
    # the plateau (tau0 + 2.5 W). Bins beyond get zero weight via masking (set to model later).
    right = tau0 + np.maximum((right_sigmas if model == "pulse" else 2.5) * W, 3.0 * w)
    mask = C <= right[:, None]
    # scale amplitudes to O(1) for conditioning
    scale = np.maximum(a0, 1e-300)
    Ys = Y / scale[:, None]
    p = np.stack([np.ones(n), tau0, b0 / scale], axis=1)
    JTJ, cost = np.zeros((n, 3, 3)), np.zeros(n)
    used = mask.copy()  # the window the cost and the curvature below belong to
    rows = np.arange(n)  # rows whose window still moves (each row on its own, as if fitted alone)
    for _ in range(3):
        mk = mask[rows]
        used[rows] = mk
        pr, JTJ[rows], cost[rows] = _lm(Ys[rows], C[rows], p[rows], tmpl, model, poisson=False,
                                        n_iter=30, mask=mk)
        p[rows] = pr
        if poisson:
            # IRLS in count units: weights 1/model (model in counts)
            pc = p.copy()
            pc[:, 0] *= scale
            pc[:, 2] *= scale
            pc, JTJ, cost = _lm(Y, C, pc, tmpl, model, poisson=True, n_iter=30, mask=mask)
            p = pc.copy()
            p[:, 0] /= scale
            p[:, 2] /= scale
            break
        new_right = p[rows, 1] + max((right_sigmas if model == "pulse" else 2.5) * W, 3.0 * w)
        new_mask = C[rows] <= new_right[:, None]
        moved = np.any(new_mask != mk, axis=1)
        if not moved.any():
            break
        rows = rows[moved]
        mask[rows] = new_mask[moved]
    nfit = used.sum(axis=1)
    dof = np.maximum(nfit - 3, 1)
    try:
        cov = np.linalg.pinv(JTJ)
    except np.linalg.LinAlgError:
        cov = np.full((n, 3, 3), np.nan)
    var_tau = cov[:, 1, 1]
    if poisson:
        amp = p[:, 0] * scale
        bg = p[:, 2] * scale
        chi2 = cost / dof
        g_pk = float(tmpl.pulse(np.zeros(1))[0][0]) if model == "pulse" else 1.0
        s_noise = np.sqrt(np.maximum(amp * g_pk + bg, 1.0))
    else:
        s2 = cost / dof  # residual variance in scaled units
        if sigma_noise is not None:
            s2 = np.maximum(s2, (np.asarray(sigma_noise, float) / scale) ** 2)
        # noise-free data: the arithmetic's resolution (1e-10 of the amplitude) is the noise floor
        s2 = np.maximum(s2, 1e-20)
        var_tau = var_tau * s2
        amp = p[:, 0] * scale
        bg = p[:, 2] * scale
        chi2 = s2
        s_noise = np.sqrt(s2) * scale
    g_peak = float(tmpl.pulse(np.zeros(1))[0][0]) if model == "pulse" else 1.0
    with np.errstate(over="ignore", invalid="ignore"):  # diverged rows (not found) may overflow
        snr = amp * g_peak / np.maximum(s_noise, 1e-300)
    tau = p[:, 1]
    # a window clipped at the grid's edge can leave too few bins: the fit is then exact
    # (zero residual, zero variance) and would report an onset of infinite SNR; refuse it
    found = (np.isfinite(tau) & np.isfinite(var_tau) & (var_tau > 0) & (amp > 0)
             & (np.abs(tau - tau0) < 3 * W) & (nfit >= 6)
             & (tau >= C[:, 0]) & (tau <= C[:, -1]))  # a peak outside the data: amplitude unbounded
    tau_std = np.sqrt(np.maximum(var_tau, 0)) if True else None
    return OnsetFit(tau=tau, tau_std=tau_std, amplitude=amp, background=bg, snr=snr, found=found,
                    chi2=chi2)


def onset_crb(tmpl, amplitude: float, sigma_noise: float, grid, tau: float,
              model: str = "pulse") -> float:
    """Cramer-Rao bound (std) of the onset from a whole trace with unknown amplitude and
    background under white Gaussian noise ``sigma_noise``."""
    c = grid.centers if hasattr(grid, "centers") else grid.start + (np.arange(grid.n_bins) + 0.5) * grid.bin_width
    f = tmpl.pulse if model == "pulse" else tmpl.edge
    g, dg = f(c - tau)
    J = np.stack([g, -amplitude * dg, np.ones_like(g)], axis=1)
    F = J.T @ J / sigma_noise ** 2
    return float(math.sqrt(np.linalg.inv(F)[1, 1]))


# ----------------------------------------------------------------------------- detection
def _smooth(y, tmpl, w):
    """Matched filter (correlate with the pulse template) for detection."""
    if tmpl is None:
        return y
    half = int(math.ceil(2.5 * tmpl.width / w))
    x = np.arange(-half, half + 1) * w
    k, _ = tmpl.pulse(x)
    k = k / np.sum(k * k) * np.sum(k) if np.sum(k * k) > 0 else k
    k = k / k.sum()
    from scipy.ndimage import correlate1d

    return correlate1d(y, k, axis=-1, mode="nearest")


def detect_pulses(y: np.ndarray, grid, tmpl, max_pulses: int = 1, k_sigma: float = 6.0,
                  t_min: float | None = None, poisson: bool = False, rel_min: float = 0.0,
                  model: str = "pulse", right_sigmas: float = 1.5):
    """Greedy detection of up to ``max_pulses`` families in one trace (earliest first).

    Each pass finds the earliest bin of the residual's matched-filter output above
    background + k_sigma * noise, fits the family's onset there, subtracts the fitted pulse and
    repeats after it. Returns a list of dicts (tau, tau_std, amplitude, snr). Many traces:
    ``detect_pulses_batch`` (the same passes on all traces at once)."""
    return detect_pulses_batch(np.asarray(y, float)[None], grid, tmpl, max_pulses=max_pulses,
                               k_sigma=k_sigma, t_min=t_min, poisson=poisson, rel_min=rel_min,
                               model=model, right_sigmas=right_sigmas)[0]


def detect_pulses_batch(Y: np.ndarray, grid, tmpl, max_pulses: int = 1, k_sigma: float = 6.0,
                        t_min: float | None = None, poisson: bool = False, rel_min: float = 0.0,
                        model: str = "pulse", right_sigmas: float = 1.5) -> list[list[dict]]:
    """``detect_pulses`` on every row of Y (n, n_bins): one list of dicts per row.

    Pass k runs on the rows still searching (a row stops when nothing is left above its
    threshold or a family is weaker than ``rel_min`` times its first): matched filter, first
    crossing and onset fit (``fit_onsets``, whose rows are fitted independently) for all of them
    at once, so each row gets what ``detect_pulses`` gives it alone."""
    Y = np.atleast_2d(np.asarray(Y, float))
    n, nb = Y.shape
    w = grid.bin_width
    c = grid.start + (np.arange(nb) + 0.5) * w
    sig = noise_level(Y)
    if t_min is None:
        bg = np.median(Y[:, : max(8, nb // 8)], axis=1)
    else:
        early = c < t_min
        bg = np.median(Y[:, early] if early.any() else Y, axis=1)
    resid = Y.copy()
    tlo = np.full(n, -np.inf if t_min is None else float(t_min))
    W = tmpl.width if tmpl is not None else w
    sm_noise = sig
    if tmpl is not None:
        # noise of the matched-filter output
        half = int(math.ceil(2.5 * tmpl.width / w))
        k, _ = tmpl.pulse(np.arange(-half, half + 1) * w)
        k = k / k.sum()
        sm_noise = sig * math.sqrt(float(np.sum(k * k)))
    span = int(math.ceil(8 * W / w))
    first_amp = np.zeros(n)
    has_first = np.zeros(n, bool)
    out: list[list[dict]] = [[] for _ in range(n)]
    act = np.arange(n)
    for _ in range(max_pulses):
        if act.size == 0:
            break
        sm = _smooth(resid[act], tmpl, w)
        if poisson:
            fac = np.where(sig[act] > 0, sm_noise[act] / np.maximum(sig[act], 1e-300), 1.0)
            thr = bg[act, None] + k_sigma * np.sqrt(np.maximum(sm, 1.0)) * fac[:, None]
        else:
            thr = (bg[act] + k_sigma * np.maximum(sm_noise[act], 1e-300))[:, None]
        above = (sm > thr) & (c[None, :] >= tlo[act, None])
        has = above.any(axis=1)
        act, sm, above = act[has], sm[has], above[has]
        if act.size == 0:
            break
        k = np.argmax(above, axis=1)
        if tmpl is None:
            for a, kk in zip(act, k):
                out[a].append({"tau": float(c[kk]), "tau_std": w / math.sqrt(12.0),
                               "amplitude": float(Y[a, kk] - bg[a]),
                               "snr": float((Y[a, kk] - bg[a]) / max(sig[a], 1e-300))})
                resid[a, kk] = bg[a]
                tlo[a] = c[kk] + w
            continue
        # walk to the local peak of the smoothed residual
        kp = _first_peak(sm, k, span) if model == "pulse" else k
        tau0 = c[kp]
        fit = fit_onsets(resid[act], grid, tmpl, tau0, model=model, poisson=poisson,
                         right_sigmas=right_sigmas, background=None)
        # a failed fit (diverged from the crossing: no family there, amplitudes of 1e11-1e18 were
        # seen) is neither reported nor subtracted; the search goes on after the crossing
        ok = fit.found
        failed = act[~ok]
        tlo[failed] = tau0[~ok] + 0.5 * W
        act, tau, amp = act[ok], fit.tau[ok], fit.amplitude[ok]
        tau_std, snr = fit.tau_std[ok], fit.snr[ok]
        weak = has_first[act] & (amp < rel_min * first_amp[act])
        new = ~has_first[act]
        first_amp[act[new]] = amp[new]
        has_first[act[new]] = True
        keep = ~weak
        act, tau, amp = act[keep], tau[keep], amp[keep]
        tau_std, snr = tau_std[keep], snr[keep]
        for a, t_, s_, a_, q_ in zip(act.tolist(), tau.tolist(), tau_std.tolist(), amp.tolist(), snr.tolist()):
            out[a].append({"tau": t_, "tau_std": s_, "amplitude": a_, "snr": q_})
        if model == "pulse":
            g, _ = tmpl.pulse(c[None, :] - tau[:, None])
            resid[act] -= amp[:, None] * g
        tlo[act] = tau + 0.5 * W
        act = np.sort(np.concatenate([act, failed]))
    return out


def _first_peak(sm: np.ndarray, k0: np.ndarray, span: int) -> np.ndarray:
    """Index of the first local maximum of each row of ``sm`` at or after ``k0`` (within span)."""
    n, nb = sm.shape
    win = np.clip(k0[:, None] + np.arange(span + 2)[None, :], 0, nb - 1)
    seg = np.take_along_axis(sm, win, axis=1)
    down = seg[:, 1:] < seg[:, :-1]
    first = np.where(down.any(axis=1), np.argmax(down, axis=1), np.argmax(seg, axis=1))
    return win[np.arange(n), first]


# whole-capture onsets live in stir_onsets (it builds on the functions above)
from .stir_onsets import first_onsets, second_onsets, third_onsets, trace_onsets  # noqa: E402,F401

