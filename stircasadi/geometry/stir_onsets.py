"""Onsets of whole captures: the first, second and later families of every trace of a STIR
(``first_onsets``, ``second_onsets``, ``third_onsets``, ``trace_onsets``), in chunks of traces,
built on the per-trace fitting and detection of ``onsets`` (which re-exports these).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import GeometryError
from ..progress import progress
from .onsets import (_CHUNK_SAMPLES, _first_peak, _smooth, detect_pulses, detect_pulses_batch,
                     fit_onsets, make_template, noise_level)


def _is_poisson(capture) -> bool:
    return str(capture.noise.get("model", "")).lower() == "poisson"


def first_onsets(capture, tmpl=None, **kw):
    """O1_i for every patch both illuminated and observed: (ids, O1, O1_std, snr)."""
    tmpl = tmpl if tmpl is not None else make_template(capture)
    ids = np.intersect1d(capture.ill_ids(), capture.obs_ids())
    if ids.size == 0:
        raise GeometryError("First onsets need patches that are both illuminated and observed "
                            "(diagonal traces); this capture has none in common. Known visible "
                            "points (observed_xyz) can replace them.")
    Y = np.stack([capture.trace(i, i) for i in ids])
    return ids, *_first_family(Y, capture, tmpl, **kw)


def _first_family(Y, capture, tmpl, k_sigma: float = 6.0, right_sigmas: float = 1.5,
                  model: str = "pulse"):
    grid = capture.grid
    n = Y.shape[0]
    w = grid.bin_width
    c = grid.start + (np.arange(grid.n_bins) + 0.5) * w
    poisson = _is_poisson(capture)
    sig = noise_level(Y)
    bg = np.median(Y[:, : max(8, grid.n_bins // 8)], axis=1)
    sm = _smooth(Y, tmpl, w)
    if tmpl is not None:
        half = int(math.ceil(2.5 * tmpl.width / w))
        k, _ = tmpl.pulse(np.arange(-half, half + 1) * w)
        k = k / k.sum()
        smn = sig * math.sqrt(float(np.sum(k * k)))
    else:
        smn = sig
    thr = bg + k_sigma * np.maximum(smn, 1e-300)
    if poisson:
        thr = bg + k_sigma * np.sqrt(np.maximum(bg, 1.0))
    above = sm > thr[:, None]
    has = above.any(axis=1)
    k0 = np.where(has, np.argmax(above, axis=1), 0)
    tau = np.full(n, np.nan)
    std = np.full(n, np.nan)
    snr = np.zeros(n)
    if not has.any():
        return tau, std, snr
    if tmpl is None:
        tau[has] = c[k0[has]]
        std[has] = w / math.sqrt(12.0)
        snr[has] = (Y[has, k0[has]] - bg[has]) / np.maximum(sig[has], 1e-300)
        return tau, std, snr
    kp = _first_peak(sm, k0, int(math.ceil(8 * tmpl.width / w))) if model == "pulse" else k0
    fit = fit_onsets(Y[has], grid, tmpl, c[kp[has]], model=model, poisson=poisson,
                     right_sigmas=right_sigmas)
    ok = fit.found
    idx = np.flatnonzero(has)
    tau[idx[ok]] = fit.tau[ok]
    std[idx[ok]] = fit.tau_std[ok]
    # SNR against the trace's own noise level as well as the fit residual (whichever is larger):
    # a near-perfect fit of a few bins must not read as a strong return
    g_pk = float(tmpl.pulse(np.zeros(1))[0][0]) if model == "pulse" else 1.0
    snr[idx] = np.minimum(fit.snr, fit.amplitude * g_pk / np.maximum(sig[has], 1e-300))
    snr[idx[~ok]] = 0.0
    return tau, std, snr


def second_onsets(capture, tmpl=None, **kw):
    """O2[a, b] = onset of trace (ill_ids[a], obs_ids[b]) (NaN where none): (ill, obs, O2, O2_std, snr).

    Diagonal entries hold the first onsets (the earliest family of trace (i, i))."""
    tmpl = tmpl if tmpl is not None else make_template(capture)
    ill, obs = capture.ill_ids(), capture.obs_ids()
    if capture.stir is not None:
        Y = capture.stir.reshape(-1, capture.n_bins)
    else:
        Y = np.stack([capture.trace(i, j) for i in ill for j in obs])
    # chunks of ~4M samples: every row is fitted on its own, so chunking changes nothing but
    # the size of the temporaries (a 1 GB STIR at M = 500 otherwise makes several more)
    chunk = max(1, _CHUNK_SAMPLES // max(Y.shape[1], 1))
    parts = [_first_family(Y[s0:s0 + chunk], capture, tmpl, **kw)
             for s0 in progress(range(0, Y.shape[0], chunk), desc="second onsets", unit="chunk")]
    tau, std, snr = (np.concatenate(x) for x in zip(*parts))
    sh = (len(ill), len(obs))
    return ill, obs, tau.reshape(sh), std.reshape(sh), snr.reshape(sh)


def trace_onsets(y, grid, tmpl, max_pulses: int = 6, t_min=None, poisson=False, k_sigma=6.0,
                 rel_min: float = 0.0):
    """All detectable families in one trace (list of dicts, earliest first)."""
    return detect_pulses(y, grid, tmpl, max_pulses=max_pulses, t_min=t_min, poisson=poisson,
                         k_sigma=k_sigma, rel_min=rel_min)


def third_onsets(capture, tmpl=None, after: np.ndarray | None = None, max_pulses: int = 6,
                 k_sigma: float = 6.0, exclude: dict | None = None, exclude_tol: float | None = None):
    """Families after the first/second one in every trace, candidates for hidden-patch returns.

    Parameters
    ----------
    after : (n_ill, n_obs) onsets of the families already explained (first/second); third
        onsets are searched later than after + one IRF width (NaN -> whole trace).
    exclude : {(i, j): [times]} predicted returns of known (visible) paths to drop.

    Returns {(ill_id, obs_id): [dict(tau, tau_std, amplitude, snr), ...]}.
    """
    tmpl = tmpl if tmpl is not None else make_template(capture)
    ill, obs = capture.ill_ids(), capture.obs_ids()
    poisson = _is_poisson(capture)
    W = tmpl.width if tmpl is not None else capture.grid.bin_width
    tol = exclude_tol if exclude_tol is not None else 1.5 * W
    n_obs = len(obs)
    if capture.stir is not None:
        Y = capture.stir.reshape(-1, capture.n_bins)
    else:
        Y = np.stack([capture.trace(i, j) for i in ill for j in obs])
    # all traces at once, in chunks of ~4M samples to bound the temporaries
    chunk = max(1, _CHUNK_SAMPLES // max(Y.shape[1], 1))
    pulses_all: list[list[dict]] = []
    for s0 in progress(range(0, Y.shape[0], chunk), desc="third onsets", unit="chunk"):
        pulses_all += detect_pulses_batch(Y[s0:s0 + chunk], capture.grid, tmpl,
                                          max_pulses=max_pulses + 1, poisson=poisson, k_sigma=k_sigma)
    out = {}
    for a, i in enumerate(ill):
        for b, j in enumerate(obs):
            pulses = pulses_all[a * n_obs + b]
            t_after = None if after is None else after[a, b]
            keep = []
            for p in pulses:
                if t_after is not None and np.isfinite(t_after) and p["tau"] < t_after + 0.5 * W:
                    continue
                if exclude and (i, j) in exclude and any(abs(p["tau"] - t) < tol for t in exclude[(i, j)]):
                    continue
                keep.append(p)
            out[(int(i), int(j))] = keep[:max_pulses]
    return out
