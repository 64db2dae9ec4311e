"""Are the relay's returns explained? A matched-filter search of the whitened residual.

When to use: after a surface fit (``fit.fit_surface`` runs it as its ``explained returns``
check), or on raw relay traces to find where a hidden scatterer could be (the frame search of
``stir_surface``). A fit's whitened chi2 is computed over its own time window, around the
surface it found: a surface in the wrong place can leave the real returns outside that window,
or spread thinly over a window of 10^5 bins, and still reach chi2/dof = 1.00. A matched filter
sums the residual along each candidate point's path lengths over every trace, which is where a
missed return concentrates.

Equations (trace p with illuminated point L_p, observed point D_p, normals nL_p, nD_p, leg
l_p, gain g_p; X a candidate point; r_p(t) the residual, w_p(t) its inverse variance; h the
kernel, a Gaussian of std s over path length, sampled on the bins):

    a_p(X)  = g_p max(cos_L, 0) max(cos_D, 0) / (|X - L_p|^2 |X - D_p|^2)
    t_p(X)  = l_p + |X - L_p| + |X - D_p|
    num(X)  = sum_p a_p(X) (h * (w r))_p(t_p(X)),   den(X) = sum_p a_p(X)^2 (h^2 * w)_p(t_p(X))
    S(X)    = num |num| / den

(``*``: correlation along time; values at t_p by linear interpolation between bin centres.)
S is the chi2 decrease of the best single point scatterer at X (the hidden element's own
cosines taken as 1) whose return has the kernel's shape: for residuals that are noise alone and
traces whose noise is uncorrelated in time, S(X) ~ chi2_1 at every X, signed by the fitted
amplitude (negative S: the model predicts more than the data hold). Over K candidate points
the largest exceeds ``chi2.isf(p / K, 1)`` with probability <= p (Bonferroni; conservative,
the K scores are correlated).

Neglects: the candidate's own cosines and area (S is a detection statistic, not a fit); a
kernel wider than the true response (chosen so that points between candidates are not missed)
costs sensitivity, never false alarms.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import correlate1d
from scipy.stats import chi2 as _chi2

from ..relay import Relay

__all__ = ["matched_filter", "search_points", "explained_returns"]


def _kernel(s_bins: float) -> np.ndarray:
    half = max(int(math.ceil(4.0 * s_bins)), 1)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / max(s_bins, 1e-9)) ** 2)
    return k / k.max()


def matched_filter(relay: Relay, traces: np.ndarray, X: np.ndarray, wgt: np.ndarray | None = None,
                   kernel_sigma: float | None = None, chunk: int = 64) -> np.ndarray:
    """S(X) of the module equation for ``traces`` (P, T) on ``relay``'s geometry and time grid at
    points ``X`` (K, 3). ``wgt`` (P, T) or (P, 1): inverse variances (default: the relay's mean
    sigma); ``kernel_sigma``: the kernel's std in metres of path (default: one bin, no
    smoothing beyond a bin)."""
    g = relay.grid
    T = g.n_bins
    X = np.asarray(X, float)
    y = np.asarray(traces, float)
    if wgt is None:
        sig = float(np.mean(relay.sigma)) if relay.sigma is not None else 1.0
        wgt = np.full((y.shape[0], 1), 1.0 / (sig * sig))
    wgt = np.broadcast_to(np.asarray(wgt, float), y.shape)
    if kernel_sigma is None:
        yw, dv = y * wgt, wgt
    else:
        k = _kernel(kernel_sigma / g.bin_width)
        yw = correlate1d(y * wgt, k, axis=1, mode="constant")
        dv = correlate1d(np.ascontiguousarray(wgt), k * k, axis=1, mode="constant")
    fy = np.concatenate([yw, np.zeros((y.shape[0], 1))], axis=1).ravel()
    fd = np.concatenate([dv, np.zeros((y.shape[0], 1))], axis=1).ravel()
    num, den = np.zeros(len(X)), np.zeros(len(X))
    for p0 in range(0, relay.n_traces, chunk):
        sl = slice(p0, min(p0 + chunk, relay.n_traces))
        vL = X[None] - relay.L[sl, None]
        vD = X[None] - relay.D[sl, None]
        dL, dD = np.linalg.norm(vL, axis=-1), np.linalg.norm(vD, axis=-1)
        cL = np.maximum(np.einsum("pkd,pd->pk", vL, relay.nL[sl]) / dL, 0.0)
        cD = np.maximum(np.einsum("pkd,pd->pk", vD, relay.nD[sl]) / dD, 0.0)
        a = relay.gain[sl, None] * cL * cD / (dL * dL * dD * dD)
        pos = (relay.leg[sl, None] + dL + dD - g.start) / g.bin_width - 0.5
        i0 = np.floor(pos).astype(np.int64)
        fr = pos - i0
        bad = (i0 < 0) | (i0 >= T - 1)
        i0[bad] = T
        rows = (np.arange(sl.start, sl.stop) * (T + 1))[:, None]
        i1 = np.where(bad, T, i0 + 1) + rows
        i0 = i0 + rows
        num += np.sum(a * (fy[i0] + (fy[i1] - fy[i0]) * fr), axis=0)
        den += np.sum(a * a * (fd[i0] + (fd[i1] - fd[i0]) * fr), axis=0)
    return num * np.abs(num) / np.maximum(den, 1e-300)


def search_points(relay: Relay, also: np.ndarray | None = None, margin: float = 0.5, n: int = 32):
    """Candidate points: a world-aligned grid of ``n`` per axis over the bounding box of the
    relay's points and ``also`` (e.g. the fitted surface's), grown by ``margin`` metres on every
    side (returns from farther away are not searched). Returns (points (K, 3), spacing (3,))."""
    pts = np.vstack([relay.L, relay.D] + ([np.asarray(also, float).reshape(-1, 3)] if also is not None else []))
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    ax = [np.linspace(lo[k], hi[k], n) for k in range(3)]
    G = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    return G, (hi - lo) / (n - 1)


def explained_returns(relay: Relay, resid: np.ndarray, wgt: np.ndarray, data: np.ndarray,
                      sigma: float, also: np.ndarray | None = None, p: float = 1e-3, n: int = 32,
                      margin: float = 0.5) -> dict:
    """The explained-returns check of a fit: the matched filter of the whitened ``resid`` (P, T)
    and of the ``data`` (P, T) over :func:`search_points`, with a kernel of std
    sqrt(sigma^2 + spacing^2) (``sigma``: the fitted response's width; spacing: the candidates';
    the nearest candidate's paths differ from a point's by up to sqrt(3) spacing, so a point
    between candidates is not missed). The residual holds
    unexplained returns when its largest S exceeds the noise level ``chi2.isf(p / K, 1)``.

    Returns a dict: ``passed``, ``max_residual`` (S), ``max_data``, ``ratio`` (of the two),
    ``threshold``,
    ``at`` (the point of the largest residual S), ``candidates`` (K), ``kernel_sigma_m``."""
    X, h = search_points(relay, also, margin, n)
    ks = math.sqrt(sigma ** 2 + float(np.max(h)) ** 2)
    sr = matched_filter(relay, resid, X, wgt, ks)
    sd = matched_filter(relay, data, X, wgt, ks)
    thr = float(_chi2.isf(p / len(X), 1))
    k = int(np.argmax(sr))
    mr, md = float(sr[k]), float(max(sd.max(), 0.0))
    ratio = mr / md if md > 0 else math.inf
    return {"passed": bool(mr <= thr), "max_residual": mr, "max_data": md,
            "ratio": ratio, "threshold": thr, "at": X[k].tolist(), "candidates": int(len(X)),
            "kernel_sigma_m": ks, "p": p}
