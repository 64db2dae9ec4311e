"""Impulse responses: ideal, Gaussian and measured; the bin integral, written once.

When to use
-----------
Everything that turns a light path into time bins goes through here: the numeric forward model
(``transport/deposit.py``), the symbolic CasADi model (``stircasadi.model``) and the onset
templates of the geometry stage (``stircasadi.geometry.onsets``). A capture's ``irf`` samples
become an object with :func:`from_samples` (one Gaussian test, one tolerance, for every stage);
a capture without samples gets them from its first-bounce returns with :func:`estimate_samples`.

Equations
---------
A path of amplitude ``a`` arriving at exact path length ``tau`` adds to the bin ``[t, t + w)``

    a * B(t - tau, w),      B(x, w) = H(x + w) - H(x)                           (bin integral)

with ``H`` the cumulative impulse response (unit area, centred on the path length):

* ``IdealIRF``: H = step (the whole amplitude lands in the bin that holds tau).
* ``GaussianIRF(fwhm)``: H(x) = Phi(x / sigma), sigma = fwhm / (2 sqrt(2 ln 2)); the default
  FWHM is 210 ps (6.3 cm of path), the paper's photodiode and 5 GHz sampling scope. On CasADi
  symbols ``B`` is ``(erf((x + w) c) - erf(x c)) / 2`` with ``c = 1 / (sqrt 2 sigma)``: a smooth
  function of tau, so delays are differentiable.
* ``ArrayIRF(samples, bin_width)``: a measured response sampled on bins of ``bin_width`` with its
  peak at the centre sample. H is the monotone (PCHIP) interpolant of the cumulative sums at the
  bin edges: its bin integrals reproduce the samples exactly, its density is continuous and
  never negative. NumPy only (a measured response makes delays non-differentiable: the model
  then keeps positions fixed).

The onset template of a bin centred at offset ``x`` from the path is
``pulse(x) = B(x - w/2, w)`` (and the running integral ``edge`` for an extended surface).

Neglects: a response that changes from trace to trace, and the response's own time origin
(taken as centred, as DESIGN.md section 4 requires).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.special import ndtr

from . import _backend as B
from .constants import ps_to_m
from .errors import SensorError

__all__ = ["IdealIRF", "GaussianIRF", "ArrayIRF", "IRF", "DEFAULT_FWHM", "FWHM_TO_SIGMA",
           "bin_integral", "discrete_kernel", "Template", "from_samples", "estimate_samples",
           "sampled", "is_gaussian"]

#: sigma = FWHM * FWHM_TO_SIGMA for a Gaussian
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
#: the paper's impulse response: 210 ps FWHM (reverse-biased photodiode + 5 GHz sampling scope)
DEFAULT_FWHM = ps_to_m(210.0)
#: a response is Gaussian when a binned Gaussian reproduces its samples within this fraction of
#: their peak (the one test every stage uses)
GAUSSIAN_TOL = 0.02
_SQ2 = math.sqrt(2.0)
_SQ2PI = math.sqrt(2.0 * math.pi)


class IdealIRF:
    """No impulse response: each path lands in the bin that contains it."""

    kind = "ideal"
    band_limited = False
    differentiable = False
    sigma = 0.0

    def cdf(self, x):
        return (np.asarray(x) > 0).astype(float)

    def pdf(self, x):
        return np.zeros_like(np.asarray(x, float))

    def support(self) -> tuple[float, float]:
        return (0.0, 0.0)

    def discrete(self, bin_width: float) -> tuple[np.ndarray, int]:
        """Kernel ``h[m]`` (m = -offset..) for a path at a bin's left edge (integer mode)."""
        return np.array([1.0]), 0

    def describe(self) -> str:
        return "none"

    def __eq__(self, other):
        return isinstance(other, IdealIRF)

    def __hash__(self):
        return hash("IdealIRF")


@dataclass(frozen=True)
class GaussianIRF:
    """Gaussian impulse response of full width at half maximum ``fwhm`` (metres of path)."""

    fwhm: float = DEFAULT_FWHM
    kind = "gaussian"
    band_limited = True
    differentiable = True

    def __post_init__(self):
        try:
            f = float(self.fwhm)
        except (TypeError, ValueError) as exc:
            raise SensorError(f"GaussianIRF fwhm must be a number of metres of path; got {self.fwhm!r}.") from exc
        if not (f > 0) or not math.isfinite(f):
            raise SensorError(f"GaussianIRF fwhm must be > 0 metres of path; got {self.fwhm!r}. "
                              "For picoseconds use GaussianIRF.from_ps(fwhm_ps).")
        object.__setattr__(self, "fwhm", f)

    @classmethod
    def from_ps(cls, fwhm_ps: float) -> "GaussianIRF":
        return cls(ps_to_m(fwhm_ps))

    @classmethod
    def from_sigma(cls, sigma: float) -> "GaussianIRF":
        return cls(sigma / FWHM_TO_SIGMA)

    @property
    def sigma(self) -> float:
        return self.fwhm * FWHM_TO_SIGMA

    def cdf(self, x):
        """H(x); NumPy (``ndtr``) or CasADi (``erf``)."""
        if B.is_symbolic(x):
            import casadi as ca
            return 0.5 * (1.0 + ca.erf(x / (_SQ2 * self.sigma)))
        return ndtr(np.asarray(x) / self.sigma)

    def pdf(self, x):
        z = np.asarray(x, float) / self.sigma
        return np.exp(-0.5 * z * z) / (_SQ2PI * self.sigma)

    def support(self) -> tuple[float, float]:
        return (-8.3 * self.sigma, 8.3 * self.sigma)  # tail mass < 1e-16

    def fourier(self, omega: np.ndarray) -> np.ndarray:
        """Fourier transform of the (centred) density, exp(-sigma^2 omega^2 / 2)."""
        return np.exp(-0.5 * (self.sigma * omega) ** 2)

    def band_limit(self, tol: float = 1e-15) -> float:
        """Angular frequency (rad per metre) above which the spectrum is below ``tol``."""
        return math.sqrt(-2.0 * math.log(tol)) / self.sigma

    def discrete(self, bin_width: float) -> tuple[np.ndarray, int]:
        return discrete_kernel(self, bin_width)

    def describe(self) -> str:
        return f"gaussian fwhm={self.fwhm:.4g} m"


@dataclass(frozen=True)
class ArrayIRF:
    """A measured impulse response sampled on bins of ``bin_width``, peak at the centre sample."""

    samples: tuple
    bin_width: float
    kind = "array"
    band_limited = False
    differentiable = True   # a smooth symbolic H exists (``symbolic_cdf``)

    def __post_init__(self):
        s = np.asarray(self.samples, dtype=float)
        if s.ndim != 1 or s.size == 0 or not np.all(np.isfinite(s)) or s.sum() <= 0 or np.any(s < 0):
            raise SensorError("ArrayIRF samples must be a non-empty 1-D array of finite, non-negative "
                              f"values with a positive sum; got shape {s.shape}.")
        if not (self.bin_width > 0) or not math.isfinite(self.bin_width):
            raise SensorError(f"ArrayIRF bin_width must be > 0 metres; got {self.bin_width!r}.")
        object.__setattr__(self, "samples", tuple((s / s.sum()).tolist()))

    @cached_property
    def _cdf_interp(self):
        from scipy.interpolate import PchipInterpolator

        s = np.asarray(self.samples)
        c = (len(s) - 1) / 2.0
        edges = (np.arange(len(s) + 1) - c - 0.5) * self.bin_width
        return PchipInterpolator(edges, np.concatenate([[0.0], np.cumsum(s)]), extrapolate=False)

    @property
    def sigma(self) -> float:
        """Standard deviation of the (continuous) response, metres."""
        s = np.asarray(self.samples)
        x = (np.arange(len(s)) - (len(s) - 1) / 2.0) * self.bin_width
        m = float(np.sum(x * s))
        return math.sqrt(max(float(np.sum((x - m) ** 2 * s)), 0.0))

    @property
    def fwhm(self) -> float:
        return self.sigma / FWHM_TO_SIGMA

    def cdf(self, x):
        x = np.asarray(x, float)
        lo, hi = self.support()
        v = self._cdf_interp(np.clip(x, lo, hi))
        return np.where(x <= lo, 0.0, np.where(x >= hi, 1.0, v))

    def pdf(self, x):
        x = np.asarray(x, float)
        lo, hi = self.support()
        inside = (x > lo) & (x < hi)
        return np.where(inside, self._cdf_interp(np.clip(x, lo, hi), 1), 0.0)

    def support(self) -> tuple[float, float]:
        n = len(self.samples)
        half = 0.5 * n * self.bin_width
        return (-half, half)

    def discrete(self, bin_width: float) -> tuple[np.ndarray, int]:
        return discrete_kernel(self, bin_width)


    @cached_property
    def symbolic_cdf(self):
        """CasADi function H(x): cubic B-spline through the PCHIP cdf on a grid of w/8, flat
        (0, 1) for two response widths beyond the support."""
        import casadi as ca

        lo, hi = self.support()
        pad = 2.0 * (hi - lo)
        x = np.linspace(lo - pad, hi + pad, int(round((hi - lo + 2 * pad) / (self.bin_width / 8))) + 1)
        return ca.interpolant("irf_cdf", "bspline", [x.tolist()], self.cdf(x).tolist())

    def describe(self) -> str:
        return f"measured ({len(self.samples)} samples, fwhm~{self.fwhm:.4g} m)"


IRF = IdealIRF | GaussianIRF | ArrayIRF


def bin_integral(irf: IRF, left, width: float):
    """``H(left + width) - H(left)``: the share of a unit path at offset ``-left`` from a bin's left
    edge that lands in a bin of ``width`` (``left`` = bin left edge - path length). NumPy arrays,
    or CasADi symbols for a ``GaussianIRF``: the one bin integral of the project."""
    if B.is_symbolic(left):
        import casadi as ca
        if isinstance(irf, ArrayIRF):
            H = irf.symbolic_cdf
            lo, hi = irf.support()
            pad = 2.0 * (hi - lo)

            def h(v):  # constant beyond the spline's grid (its extrapolation is linear)
                return H(ca.fmin(ca.fmax(v, lo - pad), hi + pad))
            shp = left.shape
            a, b = ca.vec(left + width).T, ca.vec(left).T
            return ca.reshape(h(a) - h(b), shp[0], shp[1])
        if not isinstance(irf, GaussianIRF):
            raise SensorError(f"A symbolic (differentiable) bin integral needs a Gaussian or a "
                              f"measured response; got {irf.describe()}.")
        c = 1.0 / (_SQ2 * irf.sigma)
        return 0.5 * (ca.erf((left + width) * c) - ca.erf(left * c))
    return irf.cdf(np.asarray(left) + width) - irf.cdf(left)


def discrete_kernel(irf: IRF, bin_width: float) -> tuple[np.ndarray, int]:
    """Kernel ``h[m] = H((m+1) w) - H(m w)`` over the response's support, and the index of m = 0:
    how a path at a bin's left edge spreads over bins (integer-delay mode)."""
    lo, hi = irf.support()
    m = np.arange(math.floor(lo / bin_width) - 1, math.ceil(hi / bin_width) + 1)
    return bin_integral(irf, m * bin_width, bin_width), int(-m[0])


def sampled(irf: IRF, bin_width: float) -> np.ndarray | None:
    """The response on bins of ``bin_width`` with its peak at the centre sample (a Capture's
    ``irf`` dataset); None for the ideal response."""
    if isinstance(irf, IdealIRF):
        return None
    lo, hi = irf.support()
    half = int(math.ceil(max(-lo, hi) / bin_width))
    x = np.arange(-half, half + 1) * bin_width
    return bin_integral(irf, x - 0.5 * bin_width, bin_width)


@dataclass(frozen=True)
class Template:
    """The response seen through bins of width ``w``: what the onset fits and detectors use.

    ``pulse(x)`` is the bin integral for a bin centred ``x`` after the path (value and derivative
    with respect to x); ``edge(x)`` its running integral per bin (an extended surface: a step
    blurred by the response). ``width`` = sqrt(sigma^2 + w^2 / 12), the binned response's std.
    """

    irf: GaussianIRF | ArrayIRF
    w: float

    @property
    def sigma(self) -> float:
        return self.irf.sigma

    @property
    def width(self) -> float:
        return math.sqrt(self.irf.sigma ** 2 + self.w ** 2 / 12.0)

    def pulse(self, x):
        h = self.w / 2
        x = np.asarray(x, float)
        return self.irf.cdf(x + h) - self.irf.cdf(x - h), self.irf.pdf(x + h) - self.irf.pdf(x - h)

    def edge(self, x):
        x = np.asarray(x, float)
        h = self.w / 2
        if isinstance(self.irf, GaussianIRF):
            s = self.irf.sigma

            def psi(z):
                return z * ndtr(z) + np.exp(-0.5 * z * z) / _SQ2PI
            val = s / self.w * (psi((x + h) / s) - psi((x - h) / s))
        else:  # running integral of H by the trapezoid rule on a fine grid
            val = _integrated_cdf(self.irf, x + h) - _integrated_cdf(self.irf, x - h)
            val = val / self.w
        return val, (self.irf.cdf(x + h) - self.irf.cdf(x - h)) / self.w

    def support(self) -> tuple[float, float]:
        r = 5.0 * self.width
        return -r, r


def _integrated_cdf(irf: ArrayIRF, x):
    """int_{lo}^{x} H(u) du for a measured response (exact to the fine grid's trapezoids)."""
    lo, hi = irf.support()
    u = np.linspace(lo, hi, 64 * len(irf.samples) + 1)
    Hu = irf.cdf(u)
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (Hu[1:] + Hu[:-1]) * np.diff(u))])
    x = np.asarray(x, float)
    return np.where(x >= hi, cum[-1] + (x - hi), np.interp(x, u, cum, left=0.0))


def is_gaussian(samples, bin_width: float, tol: float = GAUSSIAN_TOL) -> GaussianIRF | None:
    """The Gaussian whose bin integrals reproduce ``samples`` (peak at the centre) within ``tol``
    of their peak, found by least squares on sigma (moments fail below a bin); else None."""
    from scipy.optimize import minimize_scalar

    s = np.asarray(samples, float)
    s = s / s.sum()
    x = (np.arange(len(s)) - (len(s) - 1) / 2.0) * bin_width
    mu = float(np.sum(x * s))

    def binned(sig):
        return bin_integral(GaussianIRF.from_sigma(sig), x - 0.5 * bin_width, bin_width)

    res = minimize_scalar(lambda ls: float(np.sum((binned(math.exp(ls)) - s) ** 2)),
                          bounds=(math.log(bin_width * 1e-3), math.log(bin_width * len(s))),
                          method="bounded", options={"xatol": 1e-10})
    sigma = math.exp(res.x)
    # polish: Brent stops at ~sqrt(eps) in log sigma (5e-9 relative), which a 1e-9 noise floor sees
    from scipy.optimize import least_squares
    pol = least_squares(lambda ls: binned(math.exp(ls[0])) - s, [math.log(sigma)], xtol=1e-15,
                        ftol=1e-15, gtol=1e-15, method="lm")
    sigma = math.exp(float(pol.x[0]))
    if abs(mu) < 0.25 * bin_width and np.max(np.abs(binned(sigma) - s)) <= tol * s.max():
        return GaussianIRF.from_sigma(sigma)
    return None


def from_samples(samples, bin_width: float, tol: float = GAUSSIAN_TOL) -> IRF:
    """An impulse-response object from a Capture's ``irf`` samples (peak at the centre sample):
    a ``GaussianIRF`` when one reproduces them within ``tol`` (delays stay differentiable),
    the ideal response for a one-bin response, else an ``ArrayIRF``."""
    s = np.asarray(samples, float)
    if s.ndim != 1 or s.size == 0 or not np.all(np.isfinite(s)) or s.sum() <= 0:
        raise SensorError(f"irf samples must be a non-empty 1-D array of finite values with a "
                          f"positive sum; got shape {s.shape}.")
    s = np.clip(s, 0.0, None)
    if np.count_nonzero(s > 1e-6 * s.max()) <= 1:
        return IdealIRF()
    g = is_gaussian(s, bin_width, tol)
    return g if g is not None else ArrayIRF(tuple((s / s.sum()).tolist()), bin_width)


def estimate_samples(traces: np.ndarray, half_bins: int = 40, frac: float = 0.3,
                     min_traces: int = 1, trim: bool = True) -> np.ndarray | None:
    """The impulse response from first-bounce returns: each trace's first local peak above
    ``frac`` of its maximum (background = its median removed) is located below the bin (a
    parabola through three bins), its window of ``2 half_bins + 1`` bins is shifted onto the
    bin centre (a Fourier shift: the response is smooth) and normalised, and the windows are
    averaged; with ``trim`` only the central lobe is kept (down to 1e-3 of the peak: later
    families of other traces average out). Peak at the centre sample; None when fewer than
    ``min_traces`` traces have a usable first peak."""
    tr = np.atleast_2d(np.asarray(traces, float))
    L = 2 * half_bins + 1
    pad = half_bins
    acc, n = np.zeros(L), 0
    freq = np.fft.rfftfreq(L + 2 * pad)
    for y in tr:
        y = y - np.median(y)
        m = y.max()
        if not m > 0:
            continue
        k0 = int(np.flatnonzero(y >= frac * m)[0])
        k = k0 + int(np.argmax(y[k0:k0 + max(3, half_bins // 2)]))
        if k < half_bins + pad or k + half_bins + pad >= len(y):
            continue
        a_, b_, c_ = y[k - 1], y[k], y[k + 1]
        den = a_ - 2 * b_ + c_
        delta = 0.5 * (a_ - c_) / den if den < 0 else 0.0
        seg = y[k - half_bins - pad:k + half_bins + pad + 1]
        seg = np.fft.irfft(np.fft.rfft(seg) * np.exp(2j * np.pi * freq * delta), n=len(seg))[pad:pad + L]
        if seg.sum() > 0:
            acc += seg / seg.sum()
            n += 1
    if n < max(min_traces, 1):
        return None
    acc /= n
    if not trim:
        out = np.clip(acc, 0, None)
        return out / out.sum() if out.sum() > 0 else None
    k0 = half_bins
    lo = k0
    while lo > 0 and acc[lo - 1] > 1e-3 * acc[k0]:
        lo -= 1
    hi = k0
    while hi < len(acc) - 1 and acc[hi + 1] > 1e-3 * acc[k0] and acc[hi + 1] <= acc[hi] * 1.05:
        hi += 1
    r = max(k0 - lo, hi - k0)
    out = np.clip(acc[k0 - r:k0 + r + 1], 0, None)
    return out / out.sum() if out.sum() > 0 else None
