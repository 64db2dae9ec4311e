"""The sensor response of the surface fit: a Gaussian core, an exponential tail, slow tails.

When to use: ``model.SurfaceModel`` deposits every (trace, node) path through the CORE of one of
these shapes and then applies the SLOW tails to each trace as a linear filter; ``fit.fit_surface``
fits the core's width and tail and the slow tails' weights. A single-photon detector's response
has a sharp peak and diffusion tails that last far longer than the peak (on the Stanford scans
3 cm and 12 cm of path, holding most of the counts); a symmetric Gaussian fitted to it moves the
fitted delays into the tail (the Stanford charts came out centimetres too far).

Equations (x = bin edge - path length, metres of path; s the core's Gaussian std, which per pair
includes the node cell's own delay spread: s^2 = sigma^2 + c^2):

* core ``gaussian``: F(x) = Phi(x / s), f = phi(x / s) / s, f' = -x f / s^2 (the same H as
  ``irf.GaussianIRF``; the tests check the two agree).
* core ``emg`` (exponentially modified Gaussian, tail length tau):

      F(x) = Phi(x / s) - T(x),  T(x) = exp(s^2 / (2 tau^2) - x / tau) Phi(x / s - s / tau),
      f(x) = T(x) / tau,          f'(x) = (phi(x / s) / s - f(x)) / tau,
      dF/dtau = -(f(x) (x / tau - s^2 / tau^2) + phi(x / s) s / tau^2),

  with T written through ``erfcx`` where the exponential would overflow.
* slow tails (``slow`` = ((tau_i, beta_i), ...)): the response is core * [(1 - sum beta) delta +
  sum beta_i Exp(tau_i)]. On a trace of binned core deposits G_k the tail is the filter

      E_i(G)_k = K0 G_k + c sum_{j<k} r^(k-1-j) G_j,  r = exp(-w / tau_i),
      K0 = 1 - (tau_i / w)(1 - r),  c = (tau_i / w)(1 - r)^2,

  the exact transfer of a bin's content spread evenly over the bin (an error of order w / tau_i
  on where inside a bin the tail starts: use it for tails much longer than a bin).

For every core dF/ds = s f'(x) (the heat equation of the Gaussian factor). The time origin is the
MODE of the whole response (its peak), not the Gaussian's centre: the Stanford and CC-SOCR files
are rectified by putting the direct return's peak at t = 0, and DESIGN.md centres every response
on its peak; ``mode_offset`` gives m0 >= 0 with x_model = x + m0.
Neglects: a response that changes with count rate (pile-up) or from trace to trace.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter
from scipy.special import erfcx, ndtr

from ...errors import ReconstructionError

__all__ = ["Response", "KINDS"]

KINDS = ("gaussian", "emg")
_SQ2 = math.sqrt(2.0)
_ISQ2PI = 1.0 / math.sqrt(2.0 * math.pi)


def _phi(u):
    return _ISQ2PI * np.exp(-0.5 * u * u)


def _emg_T(x, s, tau):
    """T(x) = exp(s^2/(2 tau^2) - x/tau) Phi(x/s - s/tau), overflow-free."""
    x, s = np.broadcast_arrays(np.asarray(x, float), np.asarray(s, float))
    u = x / s - s / tau
    out = np.empty(x.shape)
    n = u < 0
    # u < 0: exp(...) Phi(u) = 0.5 erfcx(-u / sqrt 2) exp(-x^2 / (2 s^2))
    out[n] = 0.5 * erfcx(-u[n] / _SQ2) * np.exp(-0.5 * (x[n] / s[n]) ** 2)
    p = ~n
    out[p] = np.exp(0.5 * (s[p] / tau) ** 2 - x[p] / tau) * ndtr(u[p])
    return out


def _emg_pdf(x, s, tau):
    return _emg_T(x, s, tau) / tau


@dataclass(frozen=True)
class Response:
    """A response: core ``kind`` ("gaussian" or "emg"), ``sigma`` (the core's Gaussian std,
    metres of path), ``tail`` (the core's exponential tail, metres; emg only) and ``slow``
    (((tau_i, beta_i), ...): slow tails applied per trace)."""

    kind: str
    sigma: float
    tail: float = 0.0
    slow: tuple = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ReconstructionError(f"response kind must be one of {KINDS}; got {self.kind!r}.")
        if not (self.sigma > 0 and math.isfinite(self.sigma)):
            raise ReconstructionError(f"response sigma must be > 0 metres of path; got {self.sigma!r}.")
        if self.kind == "emg" and not (self.tail > 0 and math.isfinite(self.tail)):
            raise ReconstructionError(f"an 'emg' response needs a tail > 0 metres of path; got {self.tail!r}.")
        for tau, beta in self.slow:
            if not (tau > 0 and 0 <= beta < 1):
                raise ReconstructionError(f"slow tails need tau > 0 and 0 <= beta < 1; got {self.slow!r}.")
        if sum(b for _, b in self.slow) >= 1:
            raise ReconstructionError(f"the slow tails' weights must sum below 1; got {self.slow!r}.")

    def with_params(self, sigma: float, tail: float | None = None, betas=None) -> "Response":
        slow = self.slow if betas is None else tuple((t, float(b)) for (t, _), b in zip(self.slow, betas))
        return Response(self.kind, float(sigma), float(self.tail if tail is None else tail), slow)

    # ------------------------------------------------------------------ the core, per pair
    def support(self, s_max: float) -> tuple[float, float]:
        """(left, right) offsets from the path length beyond which the CORE is negligible
        (below ~1e-7 of its mass) for per-pair widths up to ``s_max``."""
        m0 = self.mode_offset()
        if self.kind == "gaussian":
            return -5.5 * s_max - m0, 5.5 * s_max - m0
        return -5.5 * s_max - m0, 5.5 * s_max + 16.0 * self.tail - m0

    def parts(self, x, s, need_tail: bool = False, rows=None):
        """The core's (F, f, f') at offsets ``x`` (already shifted by the mode) for Gaussian
        widths ``s`` (broadcast); with ``need_tail`` also dF/dtail (zeros for a Gaussian).
        ``rows``: F at every row of ``x`` (its first axis), the others at these rows only (the
        same numbers there; ``s`` then has ``x``'s shape)."""
        x = np.asarray(x, float)
        s = np.asarray(s, float)
        F = None
        if rows is not None:
            F = self.cdf(x, s)
            x, s = np.take(x, rows, axis=0), np.take(s, rows, axis=0)
        u = x / s
        ph = _phi(u)
        if self.kind == "gaussian":
            F = ndtr(u) if F is None else F
            f = ph / s
            f1 = -u / s * f
            return (F, f, f1, np.zeros_like(f)) if need_tail else (F, f, f1)
        tau = self.tail
        T = _emg_T(x, s, tau)
        F = ndtr(u) - T if F is None else F
        f = T / tau
        f1 = (ph / s - f) / tau
        if not need_tail:
            return F, f, f1
        Ft = -(f * (x / tau - (s / tau) ** 2) + ph * s / tau ** 2)
        return F, f, f1, Ft

    def cdf(self, x, s):
        """The core's F alone (``parts``' first output, without its densities)."""
        x = np.asarray(x, float)
        s = np.asarray(s, float)
        F = ndtr(x / s)
        return F if self.kind == "gaussian" else F - _emg_T(x, s, self.tail)

    def cdf_bins(self, left, width: float, s: float | None = None) -> np.ndarray:
        """The core's bin integrals F(left + width) - F(left) at bin left edges ``left``
        relative to the path length (the mode's shift applied)."""
        s = self.sigma if s is None else s
        m0 = self.mode_offset()
        left = np.asarray(left, float)
        return self.parts(left + width + m0, s)[0] - self.parts(left + m0, s)[0]

    # ------------------------------------------------------------------ the whole response
    def pdf(self, x, s: float | None = None) -> np.ndarray:
        """The whole response's density at offsets ``x`` from the Gaussian centre (no mode
        shift), core width ``s`` (default sigma)."""
        s = self.sigma if s is None else s
        x = np.asarray(x, float)
        core = _phi(x / s) / s if self.kind == "gaussian" else _emg_pdf(x, s, self.tail)
        out = (1.0 - sum(b for _, b in self.slow)) * core
        for tau, beta in self.slow:
            if self.kind == "gaussian":
                out = out + beta * _emg_pdf(x, s, tau)
            elif abs(tau - self.tail) < 1e-9 * tau:
                raise ReconstructionError("a slow tail equal to the core's tail is degenerate; "
                                          "drop it or change its length.")
            else:
                out = out + beta * (self.tail * _emg_pdf(x, s, self.tail)
                                    - tau * _emg_pdf(x, s, tau)) / (self.tail - tau)
        return out

    def mode_offset(self) -> float:
        """m0: the whole response's mode after the Gaussian centre (0 for a bare Gaussian)."""
        if self.kind == "gaussian" and not self.slow:
            return 0.0
        return _mode(self)

    def d_mode(self) -> np.ndarray:
        """dm0 / d(sigma, tail, beta_1, ...) by central differences of the (smooth) mode."""
        base = [self.sigma, self.tail] + [b for _, b in self.slow]
        out = np.zeros(len(base))
        if self.kind == "gaussian" and not self.slow:
            return out
        for i, v in enumerate(base):
            if i == 1 and self.kind == "gaussian":
                continue
            h = 1e-5 * (v if v > 0 else 1e-3)
            lo, hi = list(base), list(base)
            lo[i], hi[i] = max(v - h, 0.0), v + h          # weights stay >= 0 at their bound
            out[i] = (_mode(self._from(hi)) - _mode(self._from(lo))) / (hi[i] - lo[i])
        return out

    def _from(self, vals) -> "Response":
        return Response(self.kind, vals[0], vals[1], tuple((t, b) for (t, _), b in zip(self.slow, vals[2:])))

    def fwhm(self) -> float:
        """Full width at half maximum of the whole response (metres of path; numeric)."""
        from ...irf import FWHM_TO_SIGMA
        if self.kind == "gaussian" and not self.slow:
            return self.sigma / FWHM_TO_SIGMA
        lo = -6.0 * self.sigma
        hi = 6.0 * self.sigma + 8.0 * max([self.tail] + [t for t, _ in self.slow])
        x = np.linspace(lo, hi, 40001)
        f = self.pdf(x)
        above = np.flatnonzero(f >= 0.5 * f.max())
        return float(x[above[-1]] - x[above[0]])

    # ------------------------------------------------------------------ the slow tails, per trace
    def tail_filter(self, G: np.ndarray, w: float, adjoint: bool = False, axis: int = -1) -> np.ndarray:
        """Apply [(1 - sum beta) + sum beta_i E_i] along ``axis`` of ``G`` (binned core
        deposits, bin width ``w``); ``adjoint`` applies its transpose."""
        if not self.slow:
            return G
        if G.ndim > 1 and axis % G.ndim != G.ndim - 1:
            return _fused_tails(G, self.slow, w, adjoint, axis)
        out = (1.0 - sum(b for _, b in self.slow)) * G
        for tau, beta in self.slow:
            out += beta * exp_filter(G, tau, w, adjoint, axis)
        return out

    def describe(self) -> str:
        core = (f"gaussian sigma={self.sigma:.4g} m" if self.kind == "gaussian"
                else f"emg sigma={self.sigma:.4g} m tail={self.tail:.4g} m")
        slow = "".join(f" + {b:.3g} x exp({t:.4g} m)" for t, b in self.slow)
        return core + slow + " (mode-centred)"


def _exp_coefficients(tau: float, w: float) -> tuple[float, float, float]:
    """(r, K0, c) of the module docstring's filter E for tail ``tau`` and bin width ``w``."""
    r = math.exp(-w / tau)
    return r, 1.0 - (tau / w) * (1.0 - r), (tau / w) * (1.0 - r) ** 2


def exp_filter(G: np.ndarray, tau: float, w: float, adjoint: bool = False, axis: int = -1) -> np.ndarray:
    """E(G) of the module docstring along ``axis`` (``adjoint``: its transpose)."""
    r, K0, c = _exp_coefficients(tau, w)
    dt = G.dtype if G.dtype in (np.float32, np.float64) else np.float64
    b, a = np.array([0.0, c], dt), np.array([1.0, -r], dt)
    if adjoint:
        Gr = np.flip(G, axis)
        return np.flip(K0 * Gr + lfilter(b, a, Gr, axis=axis), axis)
    out = lfilter(b, a, G, axis=axis)
    out += K0 * G
    return out


def _fused_tails(G: np.ndarray, slow, w: float, adjoint: bool, axis: int) -> np.ndarray:
    """``tail_filter`` along a leading ``axis`` (the Jacobian's time axis, (traces, bins,
    columns)): every slow tail's recursion E_i(G)_k = K0 G_k + acc_k, acc_(k+1) = r acc_k + c G_k,
    run together, one step per bin over the (traces, columns) slab (contiguous rows): the same
    recursion as ``exp_filter``'s ``lfilter``, which along a non-last axis is ~3x slower per tail.
    ``adjoint`` runs it from the last bin backwards (the transpose)."""
    out = np.empty_like(G)
    O, X = np.moveaxis(out, axis, 0), np.moveaxis(G, axis, 0)
    rs, cs, bs = [], [], []
    a0 = 1.0 - sum(b for _, b in slow)
    for tau, beta in slow:
        r, K0, c = _exp_coefficients(tau, w)
        a0 += beta * K0
        rs.append(r)
        cs.append(c)
        bs.append(beta)
    acc = [np.zeros(X.shape[1:], G.dtype) for _ in slow]
    tmp = np.empty(X.shape[1:], G.dtype)
    n = X.shape[0]
    for k in (range(n - 1, -1, -1) if adjoint else range(n)):
        ok = O[k]
        np.multiply(X[k], a0, out=ok)
        for a, r, c, b in zip(acc, rs, cs, bs):
            np.multiply(a, b, out=tmp)
            ok += tmp
            a *= r
            np.multiply(X[k], c, out=tmp)
            a += tmp
    return out


def _mode(resp: Response) -> float:
    """The whole response's mode (offset from the Gaussian centre): a fine grid, refined by a
    parabola through the three best samples, then Newton steps on f' = 0 (smooth in the
    parameters, which ``d_mode`` differentiates)."""
    s = resp.sigma
    hi = 4.0 * s + (2.0 * resp.tail if resp.kind == "emg" else 0.0)
    x = np.linspace(-2.0 * s, hi, 4001)
    f = resp.pdf(x)
    k = int(np.clip(np.argmax(f), 1, len(x) - 2))
    a, b, c = f[k - 1], f[k], f[k + 1]
    den = a - 2 * b + c
    off = 0.5 * (a - c) / den if den < 0 else 0.0
    xm = float(x[k] + off * (x[1] - x[0]))
    d = 1e-4 * s
    for _ in range(3):
        fm, f0, fp = resp.pdf(np.array([xm - d, xm, xm + d]))
        den = fp - 2 * f0 + fm
        if not den < 0:
            break
        xm -= 0.5 * d * (fp - fm) / den
    return xm
