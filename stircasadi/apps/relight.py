"""Relighting from the measured STIR alone: superposition of the LTI system.

When to use
-----------
To see the scene under an illumination it was never measured with (several patches lit at
once, with weights, delays and temporal pulse shapes; or continuous light) using nothing but the
measured STIR: no geometry, no reflectance, no model. Relighting from an *estimate* (patches
never lit, a source elsewhere, a camera elsewhere) is ``stircasadi.apps.render``.

Equation
--------
Light transport is linear and time-invariant (the paper, section 3), so the STIR is the impulse
response of the MIMO system from "pulse aimed at patch i" to "radiance of patch j". An
illumination that emits ``w_i p_i(t - d_i)`` toward patch i (weight ``w_i``, pulse shape ``p_i``
sampled on the grid's bins, delay ``d_i`` in metres of path) gives

    y_j(t) = sum_i w_i (p_i * stir[i, j])(t - d_i)                             (transient)
    Y_j    = sum_i w_i (sum_l p_i[l]) (sum_k stir[i, j, k])                      (steady state)

A delay that is a whole number of bins is applied exactly (an index shift); a fractional
remainder is applied as a phase ramp on a zero-padded DFT, exact when the traces are band-limited
on the grid (a Gaussian impulse response several bins wide): ``fractional_error_bound`` in the
result is the impulse response's spectral magnitude at the Nyquist frequency, the relative error
this shift can make (1.0 when the response is unknown or not band-limited, e.g. ideal binning).

What it neglects: light the STIR did not record. The transient is returned on the STIR's own grid,
where every term is recorded; contributions pushed past the last bin by a delay are dropped, and
the steady state sums only the light inside the grid.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sfft

from ..errors import IlluminationError
from ..timegrid import TimeGrid

__all__ = ["Illumination", "Relit", "superpose", "relight_capture", "nayar_patterns"]


@dataclass
class Illumination:
    """An illumination pattern over the patches a pulse can be aimed at.

    Parameters
    ----------
    weights : one energy weight per entry (dimensionless; 1 = the STIR's own pulse energy).
    ids : patch ids the weights belong to; None means one weight per illuminated row of the
        STIR, in its order.
    delays : emission delay per entry, metres of optical path (default 0).
    pulses : temporal emission shape on the grid's bins, ``(L,)`` shared or ``(n, L)`` per entry
        (default ``[1.0]``, an impulse). Its sum is the pulse's energy in units of the STIR's.
    """

    weights: np.ndarray
    ids: np.ndarray | None = None
    delays: np.ndarray | None = None
    pulses: np.ndarray | None = None

    def resolve(self, ill_ids) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Rows, weights, delays (m) and pulses (n, L) against a STIR's illuminated ids."""
        ill_ids = np.asarray(ill_ids, int)
        w = _finite_1d("weights", self.weights)
        if self.ids is None:
            if len(w) != len(ill_ids):
                raise IlluminationError(
                    f"The illumination has {len(w)} weights but the STIR has {len(ill_ids)} "
                    f"illuminated patches (ids {ill_ids.tolist()[:20]}); give one weight per "
                    "illuminated patch in that order, or name the patches with ids=.")
            rows = np.arange(len(ill_ids))
        else:
            ids = np.asarray(self.ids)
            if ids.ndim != 1 or len(ids) != len(w):
                raise IlluminationError(f"ids and weights must have the same length; got {ids.shape} "
                                        f"ids and {len(w)} weights.")
            if len(np.unique(ids)) != len(ids):
                raise IlluminationError(f"An illumination names a patch twice: {ids.tolist()}; merge "
                                        "the entries (weights add, or use a pulse shape).")
            pos = {int(v): k for k, v in enumerate(ill_ids)}
            unknown = [int(v) for v in ids if int(v) not in pos]
            if unknown:
                raise IlluminationError(
                    f"Unknown illuminated patch id(s) {unknown}: the STIR's pulse was aimed only at "
                    f"{ill_ids.tolist()[:30]}. Relighting other patches needs an estimate "
                    "(stircasadi.apps.render / relight --estimate).")
            rows = np.array([pos[int(v)] for v in ids], int)
        d = np.zeros(len(w)) if self.delays is None else _finite_1d("delays", self.delays)
        if len(d) != len(w):
            raise IlluminationError(f"delays must have one entry per weight ({len(w)}); got {len(d)}.")
        if np.any(d < 0):
            raise IlluminationError(f"delays must be >= 0 metres of path (an emission cannot precede "
                                    f"the pulse's t = 0); got min {d.min():g}.")
        p = np.ones((1, 1)) if self.pulses is None else np.asarray(self.pulses, float)
        if p.ndim == 1:
            p = p[None, :]
        if p.ndim != 2 or p.shape[1] < 1 or p.shape[0] not in (1, len(w)):
            raise IlluminationError(f"pulses must be (L,) or ({len(w)}, L) samples per bin; got {p.shape}.")
        if not np.all(np.isfinite(p)):
            raise IlluminationError("pulses hold NaN or inf.")
        p = np.broadcast_to(p, (len(w), p.shape[1]))
        return rows, w, d, p


@dataclass
class Relit:
    """A relit response: ``transient`` (n_obs, n_bins) on ``grid`` and ``steady`` (n_obs,)."""

    transient: np.ndarray
    steady: np.ndarray
    grid: TimeGrid
    obs_ids: np.ndarray
    metadata: dict = field(default_factory=dict)


def _finite_1d(name, v) -> np.ndarray:
    try:
        a = np.atleast_1d(np.asarray(v, dtype=float))
    except (TypeError, ValueError) as exc:
        raise IlluminationError(f"{name} must be numbers; got {v!r}.") from exc
    if a.ndim != 1 or not np.all(np.isfinite(a)):
        raise IlluminationError(f"{name} must be a 1-D list of finite numbers; got {v!r}.")
    return a


def superpose(stir: np.ndarray, grid: TimeGrid, ill_ids, obs_ids, illumination: Illumination,
              irf=None) -> Relit:
    """Apply ``illumination`` to a STIR (n_ill, n_obs, n_bins) by superposition (module doc).

    ``irf`` (an impulse-response object) only sets ``fractional_error_bound``.
    """
    stir = np.asarray(stir, float)
    if stir.ndim != 3 or stir.shape[2] != grid.n_bins:
        raise IlluminationError(f"stir must be (n_illuminated, n_observed, {grid.n_bins}); got {stir.shape}.")
    rows, w, d, p = illumination.resolve(ill_ids)
    T, wb = grid.n_bins, grid.bin_width
    out = np.zeros(stir.shape[1:])
    shift = d / wb
    m_int = np.floor(shift + 1e-9).astype(int)
    frac = shift - m_int
    frac[np.abs(frac) < 1e-9] = 0.0
    for r, wi, m, f, pi in zip(rows, w, m_int, frac, p):
        if wi == 0.0 or m >= T:
            continue
        k = wi * pi
        if f == 0.0:
            out[:, m:] += _causal_conv(stir[r], k, T - m)
        else:
            out += _fourier_delay(_causal_conv(stir[r], k, T), m + f)
    steady = np.einsum("i,ijk->j", w * p.sum(axis=1), stir[rows])
    meta = {"method": "superposition", "n_lit": int(np.count_nonzero(w)),
            "integer_delays": bool(np.all(frac == 0)),
            "fractional_error_bound": 0.0 if np.all(frac == 0) else nyquist_leak(irf, wb)}
    return Relit(out, steady, grid, np.asarray(obs_ids), meta)


def relight_capture(capture, illumination: Illumination) -> Relit:
    """Superposition on a ``Capture``'s full STIR (paired/confocal traces are refused)."""
    if not capture.is_full:
        raise IlluminationError("Relighting by superposition needs the full STIR (every pulse seen "
                                "by every observed patch); this capture holds paired traces.")
    irf = None
    if capture.irf is not None:
        from ..irf import from_samples
        irf = from_samples(capture.irf, capture.grid.bin_width)
    return superpose(capture.stir, capture.grid, capture.ill_ids(), capture.obs_ids(), illumination,
                     irf=irf)


def _causal_conv(traces: np.ndarray, kernel: np.ndarray, n: int) -> np.ndarray:
    """First ``n`` samples of the causal convolution of each row with ``kernel``."""
    L = len(kernel)
    if L <= 32:
        out = np.zeros((traces.shape[0], n))
        for l, kv in enumerate(kernel):
            if kv != 0.0 and l < n:
                take = min(n - l, traces.shape[1])
                out[:, l:l + take] += kv * traces[:, :take]
        return out
    N = sfft.next_fast_len(traces.shape[1] + L)
    y = sfft.irfft(sfft.rfft(traces, N, axis=1) * sfft.rfft(kernel, N)[None, :], N, axis=1)
    res = np.zeros((traces.shape[0], n))
    res[:, :min(n, N)] = y[:, :min(n, N)]
    return res


def _fourier_delay(traces: np.ndarray, shift_bins: float) -> np.ndarray:
    """Delay rows by a real number of bins (zero-padded DFT phase ramp), same length."""
    T = traces.shape[1]
    N = sfft.next_fast_len(2 * T + int(math.ceil(shift_bins)) + 8)
    k = np.arange(N // 2 + 1)
    ramp = np.exp(-2j * math.pi * k * shift_bins / N)
    if N % 2 == 0:
        ramp[-1] = math.cos(math.pi * shift_bins)  # keep the Nyquist bin real
    return sfft.irfft(sfft.rfft(traces, N, axis=1) * ramp[None, :], N, axis=1)[:, :T]


def nyquist_leak(irf, bin_width: float) -> float:
    """Relative spectral magnitude of the impulse response at the grid's Nyquist frequency: the
    relative error a sub-bin shift of band-limited traces can make (1 if unknown)."""
    if irf is None or not getattr(irf, "band_limited", False):
        return 1.0
    return float(irf.fourier(np.array([math.pi / bin_width]))[0])


def nayar_patterns(ill_ids, layout=None) -> tuple[Illumination, Illumination]:
    """Two complementary binary patterns (Nayar et al. 2006, high-frequency illumination).

    ``layout`` gives each illuminated patch's integer cell ``(row, col)`` on a scan grid (a
    checkerboard then alternates along both axes); without it the patches alternate in id order.
    """
    ill_ids = np.asarray(ill_ids, int)
    if layout is None:
        on = (np.arange(len(ill_ids)) % 2) == 0
    else:
        lay = np.asarray(layout, int)
        if lay.shape != (len(ill_ids), 2):
            raise IlluminationError(f"layout must be (n_illuminated, 2) grid cells; got {lay.shape}.")
        on = (lay.sum(axis=1) % 2) == 0
    a = Illumination(on.astype(float), ids=ill_ids)
    b = Illumination((~on).astype(float), ids=ill_ids)
    return a, b
