"""The relay's own (direct) return: the measured response's slow tails and the background decay.

When to use: ``fit.fit_surface`` calls :func:`direct_return` on a rectified scan (t = 0 at the
wall). A confocal single-photon scan records the laser spot itself at t = 0, thousands of times
brighter than the hidden returns: that peak IS the sensor's response (a point at zero delay),
so its decay measures the response's tails, and what is left of it when the hidden returns
arrive is the background's slow decay (on the Stanford charts the pre-signal level of a trace
follows its direct peak with correlation 0.95).

Equation: the summed direct return, from its peak (the files put it at t = 0; earlier bins are
cut) to the gate, is fitted with a binned whole response of ``response.py`` (core emg (sigma,
tau_1) plus two slow tails (tau_2, beta_2), (tau_3, beta_3), mode at t = 0) plus a constant,
by weighted least squares (Poisson weights). The per-trace amplitude q_p is the trace's counts
in the first bins, normalised to a mean of 1.

Neglects: pile-up (a strong direct return is detected early more often than a weak one, which
shortens its measured tail slightly), a response that changes across the scan.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ..relay import Relay
from .response import Response, _emg_T

__all__ = ["DirectReturn", "direct_return", "response_cdf"]


@dataclass
class DirectReturn:
    """The fitted response (core and slow tails), the per-trace direct amplitude q (mean 1), the
    fit's residual (fraction of the summed return) and the bins it used."""

    response: Response
    q: np.ndarray
    rms_rel: float
    n_bins: int


def _emg_cdf(x, s, tau):
    from scipy.special import ndtr
    return ndtr(x / s) - _emg_T(x, s, tau)


def response_cdf(resp: Response, x) -> np.ndarray:
    """The whole response's CDF at offsets ``x`` from the Gaussian centre (Gaussian or emg core)."""
    from scipy.special import ndtr
    s, t1 = resp.sigma, resp.tail
    x = np.asarray(x, float)
    core = ndtr(x / s) if resp.kind == "gaussian" else _emg_cdf(x, s, t1)
    out = (1.0 - sum(b for _, b in resp.slow)) * core
    for tau, beta in resp.slow:
        if resp.kind == "gaussian":     # a Gaussian core with an exponential tail: an emg
            out = out + beta * _emg_cdf(x, s, tau)
        else:
            out = out + beta * (t1 * _emg_cdf(x, s, t1) - tau * _emg_cdf(x, s, tau)) / (t1 - tau)
    return out


def direct_return(relay: Relay, gate: float | None, min_ratio: float = 20.0) -> DirectReturn | None:
    """Fit the response to the relay's direct return (see the module docstring); None when the
    traces hold no direct peak at t = 0 (legs not removed, a gated or simulated capture) or it is
    not ``min_ratio`` times brighter than everything after the gate."""
    g = relay.grid
    if np.any(relay.leg != 0) or g.start > 0.5 * g.bin_width:
        return None
    w = g.bin_width
    s = relay.traces.sum(axis=0)
    k_gate = int(np.clip(np.ceil(((gate if gate is not None else 0.3 * g.end) - g.start) / w), 4, g.n_bins))
    head = s[:k_gate]
    if head.size < 8 or int(np.argmax(head)) > 1 or not (head.max() > 0):
        return None
    late = float(np.median(s[k_gate:])) if k_gate < g.n_bins else 0.0
    if head.max() - late < min_ratio * (max(float(np.max(s[k_gate:], initial=0.0)) - late, 1e-300)):
        return None
    t = g.start + np.arange(k_gate) * w
    y = head
    wt = 1.0 / np.sqrt(np.maximum(y, 1.0))

    def model(p):
        sig, t1, t2, t3 = np.exp(p[:4])
        b2, b3 = 1 / (1 + np.exp(-p[4])), 1 / (1 + np.exp(-p[5]))
        b2, b3 = b2 * 0.98, b3 * (0.98 - b2 * 0.98)
        resp = Response("emg", sig, t1, ((t2, b2), (t3, b3)))
        m0 = resp.mode_offset()
        F = response_cdf(resp, np.append(t, t[-1] + w) + m0)
        return math.exp(p[6]) * np.diff(F) + p[7], resp

    def res(p):
        return (model(p)[0] - y) * wt

    p0 = np.array([math.log(1.2 * w), math.log(max(0.5 * w, 1e-4)), math.log(0.03), math.log(0.12),
                   0.0, 0.0, math.log(max(float(y.sum()), 1.0)), max(late, 0.0)])
    try:
        sol = least_squares(res, p0, method="trf", x_scale="jac", max_nfev=400)
    except (ValueError, FloatingPointError):
        return None
    m, resp = model(sol.x)
    order = sorted(resp.slow)
    if abs(order[0][0] - resp.tail) < 1e-6 or abs(order[1][0] - order[0][0]) < 1e-6:
        return None
    # a core tail far below the core's width is no tail: a Gaussian core with the slow tails
    resp = (Response("gaussian", resp.sigma, 0.0, tuple(order)) if resp.tail < 0.2 * resp.sigma
            else Response("emg", resp.sigma, resp.tail, tuple(order)))
    k_q = max(2, int(math.ceil(2.0 * resp.fwhm() / w)))
    q = relay.traces[:, :k_q].sum(axis=1)
    q = q / max(float(q.mean()), 1e-300)
    return DirectReturn(resp, q, float(np.sqrt(np.mean((m - y) ** 2)) / max(float(y.max()), 1e-300)),
                        int(k_gate))
