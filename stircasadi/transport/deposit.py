"""Deposit path amplitudes into time bins through the sensor's impulse response (no rounding bias).

Bin k of observed column j receives ``a * (H(t_{k+1} - tau) - H(t_k - tau))`` for a path of
amplitude a at exact path length tau (see ``stircasadi.irf``). In integer-delay mode tau is a
whole number of bins and the discrete kernel ``h[m] = H((m+1) w) - H(m w)`` is used.
"""
from __future__ import annotations

import math

import numpy as np

from ..irf import bin_integral
from ..timegrid import TimeGrid


def kernel_support(irf, bin_width: float, integer: bool) -> tuple[float, float]:
    """Offsets (metres, relative to a path's arrival) over which its deposit can be non-zero:
    the impulse response's support, or in integer-delay mode that of its discrete kernel."""
    if not integer:
        return irf.support()
    h, off = irf.discrete(bin_width)
    return -off * bin_width, (len(h) - off) * bin_width


def deposit(out: np.ndarray, col: np.ndarray, amp: np.ndarray, tau: np.ndarray, grid: TimeGrid,
            irf, integer: bool = False, chunk: int = 1 << 20) -> None:
    """Add paths (column ``col``, amplitude ``amp``, arrival ``tau``) into ``out`` (n_cols, n_bins)."""
    n_cols, nb = out.shape
    flat = out.reshape(-1)
    w, t0 = grid.bin_width, grid.start
    if integer:
        h, off = irf.discrete(w)
        kk0 = np.rint((tau - t0) / w).astype(np.int64) - off
        offs = np.arange(len(h))
        for s in range(0, len(tau), chunk):
            sl = slice(s, s + chunk)
            k = kk0[sl, None] + offs[None, :]
            v = amp[sl, None] * h[None, :]
            _scatter(flat, col[sl], k, v, nb)
        return
    lo, hi = irf.support()
    nwin = int(math.ceil((hi - lo) / w)) + 2
    offs = np.arange(nwin)
    for s in range(0, len(tau), chunk):
        sl = slice(s, s + chunk)
        ta = tau[sl]
        k0 = np.floor((ta + lo - t0) / w).astype(np.int64)
        k = k0[:, None] + offs[None, :]
        left = t0 + k * w - ta[:, None]
        v = bin_integral(irf, left, w)
        v *= amp[sl, None]
        _scatter(flat, col[sl], k, v, nb)


def _scatter(flat, col, k, v, nb):
    ok = (k >= 0) & (k < nb)
    idx = (col[:, None] * nb + k)[ok]
    flat += np.bincount(idx, weights=v[ok], minlength=flat.size)


def bin_integer_samples(y: np.ndarray, grid: TimeGrid, irf) -> np.ndarray:
    """Bin instantaneous samples ``y[..., n]`` at t = n * bin_width (integer-delay mode).

    Sample n lands in the bin that starts at n * w and is spread by the discrete impulse
    response ``h[m]``: bin k receives sum_m h[m] y[k + s0 - (m - off)], s0 = start / w.
    """
    w = grid.bin_width
    s0 = int(round(grid.start / w))
    h, off = irf.discrete(w)
    n_s = y.shape[-1]
    out = np.zeros(y.shape[:-1] + (grid.n_bins,))
    for mi, hv in enumerate(h):
        lo = s0 - (mi - off)          # sample index feeding bin 0
        src_lo = max(lo, 0)
        dst_lo = src_lo - lo
        n_take = min(grid.n_bins - dst_lo, n_s - src_lo)
        if n_take > 0:
            out[..., dst_lo:dst_lo + n_take] += hv * y[..., src_lo:src_lo + n_take]
    return out
