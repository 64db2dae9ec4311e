"""Impulse response from non-impulse illumination: regularised deconvolution of known codes.

When to use
-----------
When the source did not send a picosecond impulse but a known waveform: a long or shaped pulse,
a pseudo-random binary code (maximum-length sequence, MLS) repeated periodically, or an
amplitude-modulated continuous wave (AMCW) at several modulation frequencies. Each record is the
scene's response ``y = u * h + noise`` to the code u; this module recovers the STIR trace h
(the impulse response) with a stated error. Identifying the LTI model from arbitrary
input/output records (several patches driven at once) is ``stircasadi.apps.sysid``.

Time axes: a code ``u[m]`` is the energy emitted at the instant ``m * bin_width`` after the
pulse's t = 0; records and the recovered STIR share one grid (start ``s0 * bin_width``), so that
``y[k] = sum_m u[m] h[k - m]`` with ``h[k]`` the STIR at time ``start + k * bin_width``.

Equations (all records of one trace share a period P; DFT index q, unnormalised DFT)
--------------------------------------------------------------------------------------
Periodic codes (MLS, AMCW) of period P give the periodic steady state ``Y_rq = U_rq H_q`` (a
circular convolution; h must fit in one period, P >= n_bins). A transient code of length L gives
a linear convolution of length N = n_bins + L - 1, the same equation with P = N (zero padding).
With R records (codes) per trace, Tikhonov (ridge) regularisation gives

    H_q = sum_r conj(U_rq) Y_rq / (S_q + lambda L_q),   S_q = sum_r |U_rq|^2,

where ``L_q = (2 sin(pi q / P))^4`` penalises the second difference of h (a roughness
penalty: the zero frequency is kept, high frequencies, where a band-limited STIR has nothing but
noise, are damped; ``penalty="ridge"`` uses L_q = 1), with lambda chosen by the data: generalised cross-validation (GCV,
``R P ||y - y_hat||^2 / (R P - sum_q f_q)^2``, ``f_q = S_q / (S_q + lambda L_q)``) or, when the
noise std sigma is known, the discrepancy principle (the in-band residual the filter can reach
equals its expected noise energy, ``n_band sigma^2``).

Stated error, per trace, from the same filter:

    noise:  Var h_k = sigma^2 / P  sum_q S_q / (S_q + lambda L_q)^2
    bias:   ||b||^2 = 1/P sum_q (lambda L_q / (S_q + lambda L_q))^2 |H_q|^2

with ``|H_q|^2`` estimated by ``|Y/U|^2 - P sigma^2 / S_q`` (clipped at 0) and sigma by the GCV
residual when not given; where the impulse response is known, ``|H_q| <= H_0 |IRF_q sinc_q|``
(a non-negative STIR seen through the response) caps that estimate. ``error_rms = sqrt(||b||^2 /
n_bins + Var h_k)`` per bin of the recovered window (the bias lies where h does).

A code is ill-conditioned when its power ``S_q`` falls below ``rcond`` x its maximum at a
frequency the STIR occupies (the band of the impulse response ``irf`` when given, else every
frequency): no regularisation can recover the response there, and it is refused (CodeError).

Neglects: noise that is not white and Gaussian (Poisson counts at high rates), a code that is
not known exactly (jitter, laser droop), non-linearity of the detector.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sfft
from scipy.optimize import minimize_scalar

from ..errors import CodeError

__all__ = ["Code", "mls", "pulse", "amcw", "simulate_records", "deconvolve", "Deconvolution",
           "DeconvolveSettings"]

# primitive feedback taps (1-based) of maximum-length LFSRs, orders 3..16
_MLS_TAPS = {3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5),
             10: (10, 7), 11: (11, 9), 12: (12, 6, 4, 1), 13: (13, 4, 3, 1), 14: (14, 5, 3, 1),
             15: (15, 14), 16: (16, 15, 13, 4)}


@dataclass(frozen=True)
class Code:
    """A known emission: ``waveform`` (energy per bin instant), periodic (one period) or not."""

    waveform: np.ndarray
    periodic: bool
    name: str = ""

    def __post_init__(self):
        w = np.asarray(self.waveform, float)
        if w.ndim != 1 or w.size < 1 or not np.all(np.isfinite(w)):
            raise CodeError(f"A code waveform must be a non-empty 1-D array of finite numbers; got "
                            f"shape {w.shape}.")
        if np.any(w < 0):
            raise CodeError("A code is light intensity: its samples must be >= 0 (an optical source "
                            "cannot emit negative light); shift a bipolar code to 0/1 levels.")
        if not w.sum() > 0:
            raise CodeError("A code that emits nothing cannot probe the scene (all samples are 0).")
        object.__setattr__(self, "waveform", w)

    @property
    def length(self) -> int:
        return len(self.waveform)


def mls(order: int) -> Code:
    """The 0/1 maximum-length sequence of period 2^order - 1 (flat spectrum but at zero
    frequency: |U_q|^2 = (P + 1) / 4 for q != 0)."""
    if order not in _MLS_TAPS:
        raise CodeError(f"MLS order must be in {min(_MLS_TAPS)}..{max(_MLS_TAPS)}; got {order!r}.")
    taps = _MLS_TAPS[order]
    state = [1] * order
    out = np.empty(2 ** order - 1)
    for k in range(len(out)):
        out[k] = state[-1]
        fb = 0
        for t in taps:
            fb ^= state[t - 1]
        state = [fb] + state[:-1]
    return Code(out, periodic=True, name=f"mls{order}")


def pulse(length: int, shape: str = "rect") -> Code:
    """A single long pulse of ``length`` bins: ``rect``, ``hann`` or ``gauss`` (sigma = L / 6),
    unit energy. A rectangular pulse has spectral zeros (at multiples of 1/L) and is refused
    where those fall inside the STIR's band; shaped pulses decay instead."""
    if not (isinstance(length, (int, np.integer)) and length >= 1):
        raise CodeError(f"pulse length must be an integer >= 1 bins; got {length!r}.")
    x = np.arange(length, dtype=float)
    if shape == "rect":
        w = np.ones(length)
    elif shape == "hann":
        w = np.sin(math.pi * (x + 0.5) / length) ** 2
    elif shape == "gauss":
        w = np.exp(-0.5 * ((x - (length - 1) / 2) / max(length / 6.0, 1e-9)) ** 2)
    else:
        raise CodeError(f"pulse shape must be 'rect', 'hann' or 'gauss'; got {shape!r}.")
    return Code(w / w.sum(), periodic=False, name=f"pulse-{shape}{length}")


def amcw(harmonics, period: int) -> list:
    """AMCW codes ``(1 + cos(2 pi m k / P)) / 2``, one per modulation harmonic m of the period
    P (bins). Each record then carries only frequencies 0 and +-m: recovering an n-bin STIR needs
    every harmonic of its band."""
    P = int(period)
    hs = [int(m) for m in np.atleast_1d(harmonics)]
    if P < 2 or not hs or any(m < 1 or m > P // 2 for m in hs):
        raise CodeError(f"AMCW harmonics must be integers in 1..{P // 2} of a period P >= 2; got {hs}.")
    k = np.arange(P)
    return [Code(0.5 * (1 + np.cos(2 * math.pi * m * k / P)), periodic=True, name=f"amcw{m}") for m in hs]


def _period(codes, n_bins: int) -> int:
    per = {c.periodic for c in codes}
    if len(per) != 1:
        raise CodeError("Do not mix periodic codes (MLS, AMCW) and single pulses in one deconvolution.")
    if per.pop():
        P = {c.length for c in codes}
        if len(P) != 1:
            raise CodeError(f"Periodic codes of one deconvolution must share a period; got {sorted(P)}.")
        P = P.pop()
        if P < n_bins:
            raise CodeError(f"The code period ({P} bins) is shorter than the response ({n_bins} bins): "
                            "successive periods would overlap (time aliasing). Use a longer code "
                            f"(MLS order >= {math.ceil(math.log2(n_bins + 1))}) or a coarser grid.")
        return P
    return n_bins + max(c.length for c in codes) - 1


def _spectra(codes, P: int) -> np.ndarray:
    return np.array([sfft.fft(np.pad(c.waveform, (0, P - c.length))) for c in codes])


def simulate_records(stir_traces: np.ndarray, codes, noise_sigma: float = 0.0,
                     rng: np.random.Generator | None = None) -> np.ndarray:
    """Records (n_codes, ..., P) of traces ``(..., n_bins)`` under each code, by (circular or
    linear) convolution, plus white Gaussian noise of std ``noise_sigma`` (the model above).
    Tests simulate records independently with ``stircasadi.apps.lti.drive_state_space``."""
    h = np.asarray(stir_traces, float)
    P = _period(codes, h.shape[-1])
    H = sfft.fft(h, P, axis=-1)
    out = np.array([sfft.ifft(H * U, axis=-1).real for U in _spectra(codes, P)])
    if noise_sigma > 0:
        out = out + (rng or np.random.default_rng(0)).normal(0.0, noise_sigma, out.shape)
    return out


@dataclass
class DeconvolveSettings:
    """How the regularisation is chosen and what counts as ill-conditioned."""

    #: ``"gcv"`` (generalised cross-validation) or ``"discrepancy"`` (needs ``sigma``)
    method: str = "gcv"
    #: a code's power below rcond x its maximum, inside the band, is refused
    rcond: float = 1e-10
    #: the band is where the impulse response's spectrum exceeds this fraction of its peak
    band_tol: float = 1e-6
    #: ``"d2"`` (second-difference roughness penalty) or ``"ridge"`` (the norm of h)
    penalty: str = "d2"

    def validate(self) -> "DeconvolveSettings":
        if self.method not in ("gcv", "discrepancy"):
            raise CodeError(f"method must be 'gcv' or 'discrepancy'; got {self.method!r}.")
        if self.penalty not in ("d2", "ridge"):
            raise CodeError(f"penalty must be 'd2' or 'ridge'; got {self.penalty!r}.")
        if not (0 < self.rcond < 1) or not (0 < self.band_tol < 1):
            raise CodeError(f"rcond and band_tol must lie in (0, 1); got {self.rcond}, {self.band_tol}.")
        return self


@dataclass
class Deconvolution:
    """Recovered traces ``h`` (..., n_bins) with the chosen ``lam``, noise ``std`` per bin and
    predicted ``error_rms`` per bin (both per trace), and ``sigma`` (given or estimated)."""

    h: np.ndarray
    lam: np.ndarray
    std: np.ndarray
    error_rms: np.ndarray
    sigma: np.ndarray
    metadata: dict = field(default_factory=dict)


def check_conditioning(codes, n_bins: int, bin_width: float | None = None, irf=None,
                       settings: DeconvolveSettings | None = None) -> dict:
    """Refuse codes whose power vanishes inside the STIR's band (module doc); return the
    figures: period, band size, smallest relative in-band power."""
    settings = (settings or DeconvolveSettings()).validate()
    P = _period(codes, n_bins)
    S = np.sum(np.abs(_spectra(codes, P)) ** 2, axis=0)
    q = np.arange(P)
    qs = np.minimum(q, P - q)
    if irf is not None and bin_width and getattr(irf, "band_limited", False):
        omega = 2 * math.pi * qs / (P * bin_width)
        band = irf.fourier(omega) > settings.band_tol
    else:
        band = np.ones(P, bool)
    rel = S / S.max()
    bad = np.flatnonzero(band & (rel < settings.rcond))
    if len(bad):
        raise CodeError(
            f"The code is ill-conditioned: its power falls below {settings.rcond:g} of its peak at "
            f"{len(bad)} of the {int(band.sum())} frequencies the STIR occupies (first at DFT index "
            f"{int(qs[bad].min())} of period {P}: {int(qs[bad].min())} cycles per period). The impulse "
            "response there cannot be recovered by any regularisation. Use a code with a flat spectrum "
            "(an MLS), a shorter or smoother pulse, AMCW at every harmonic of the band, or declare the "
            "sensor's impulse response (irf=) so only its band must be covered.")
    return {"period": P, "n_band": int(band.sum()), "min_rel_power": float(rel[band].min()),
            "band": band}


def deconvolve(records: np.ndarray, codes, n_bins: int, sigma: float | None = None,
               bin_width: float | None = None, irf=None,
               settings: DeconvolveSettings | None = None) -> Deconvolution:
    """Recover the STIR traces from ``records`` (n_codes, ..., P) of known ``codes`` (module doc).

    Parameters
    ----------
    records : one record per code; leading trace axes after the first are kept.
    codes : list of ``Code``, one per record.
    n_bins : length of the impulse response to recover (the STIR's grid).
    sigma : noise std of the records (per bin); estimated from the fit when None.
    bin_width, irf : the grid's bin width and the sensor's impulse response, which set the band
        a code must cover (without them every frequency must be covered).
    """
    settings = (settings or DeconvolveSettings()).validate()
    codes = list(codes)
    if not codes or not all(isinstance(c, Code) for c in codes):
        raise CodeError("codes must be a non-empty list of Code objects (mls, pulse, amcw).")
    y = np.asarray(records, float)
    if y.ndim < 2 or y.shape[0] != len(codes):
        raise CodeError(f"records must be (n_codes={len(codes)}, ..., n_samples); got {y.shape}.")
    if not np.all(np.isfinite(y)):
        raise CodeError("records hold NaN or inf.")
    info = check_conditioning(codes, n_bins, bin_width, irf, settings)
    P = info["period"]
    if y.shape[-1] != P:
        raise CodeError(f"Each record must hold {P} samples (the code period, or n_bins + code length "
                        f"- 1 for a pulse); got {y.shape[-1]}.")
    if settings.method == "discrepancy" and sigma is None:
        raise CodeError("The discrepancy principle needs the noise std: pass sigma=, or use method='gcv'.")
    lead = y.shape[1:-1]
    band = info.pop("band")
    R = len(codes)
    U = _spectra(codes, P)                                   # (R, P)
    Y = sfft.fft(y.reshape(R, -1, P), axis=-1)               # (R, n, P)
    S = np.where(band, np.sum(np.abs(U) ** 2, axis=0), 0.0)  # (P,); 0 outside the band
    B = np.einsum("rq,rnq->nq", np.conj(U), Y) * band        # (n, P)
    YY = np.sum(np.abs(Y) ** 2, axis=0)                      # (n, P)
    with np.errstate(divide="ignore", invalid="ignore"):
        g_all = np.where(S > 0, np.abs(B) ** 2 / np.where(S > 0, S, 1.0), 0.0)
    # ||y||^2 outside the codes' span (and everything outside the band): no filter reaches it
    e_perp = np.sum(np.clip(YY - g_all, 0.0, None), axis=1) / P
    n_tr = B.shape[0]
    qs = np.arange(P)
    Lq = (2 * np.sin(math.pi * qs / P)) ** 4 if settings.penalty == "d2" else np.ones(P)
    scale = float(np.median(S[S > 0]) / np.median(Lq[(Lq > 0) & (S > 0)]))
    lam = np.array([_choose_lambda(B[t], S, Lq, e_perp[t], R, P, scale, settings.method, sigma)
                    for t in range(n_tr)])
    D = S[None, :] + lam[:, None] * Lq[None, :]
    live = (S[None, :] > 0) & (D > 0)
    Dsafe = np.where(live, D, 1.0)
    f = np.where(live, S[None, :] / Dsafe, 0.0)
    Hh = np.where(live, B / Dsafe, 0.0)
    h = sfft.ifft(Hh, axis=-1).real[:, :n_bins]
    if sigma is None:   # noise from what no code reaches or the band excludes, else the GCV fit
        n_out = int(np.sum(~band)) + (R - 1) * P
        if n_out >= 16:
            sig = np.sqrt(e_perp / n_out)
        else:
            rss = np.array([_rss(B[t], S, Lq, e_perp[t], lam[t], P) for t in range(n_tr)])
            sig = np.sqrt(np.maximum(rss, 0) / np.maximum(R * P - f.sum(axis=1), 1.0))
    else:
        sig = np.full(n_tr, float(sigma))
    var = sig ** 2 / P * np.sum(np.where(live, S[None, :] / Dsafe ** 2, 0.0), axis=1)
    Ssafe = np.where(S > 0, S, 1.0)
    H2 = np.where(S > 0, np.abs(B / Ssafe) ** 2 - P * sig[:, None] ** 2 / Ssafe, 0.0)
    H2 = np.clip(H2, 0.0, None)
    env = _envelope(irf, bin_width, P)
    if env is not None:  # a non-negative STIR has |H_q| <= H_0 |IRF_q sinc_q| (caps the noisy plug-in)
        # H_0 (the trace's energy) at its estimate plus two of its std: a cap that stays a cap
        # when a trace is buried in the noise
        H0 = (np.abs(B[:, 0] / S[0]) + 2 * np.sqrt(P / S[0]) * sig if S[0] > 0
              else np.abs(Hh[:, 0]))
        H2 = np.minimum(H2, (H0[:, None] * env[None, :]) ** 2)
    shrink = np.where(live, lam[:, None] * Lq[None, :] / Dsafe, 1.0)
    bias2 = np.sum(shrink ** 2 * H2, axis=1) / P
    # per bin of the recovered window: the noise is white over the period, the bias lies where h does
    err = np.sqrt(bias2 / n_bins + var)
    meta = dict(info, method=settings.method, penalty=settings.penalty, n_codes=R, codes=[c.name for c in codes])
    return Deconvolution(h=h.reshape(lead + (n_bins,)), lam=lam.reshape(lead),
                         std=np.sqrt(var).reshape(lead), error_rms=err.reshape(lead),
                         sigma=sig.reshape(lead), metadata=meta)


def _envelope(irf, bin_width, P):
    """|IRF(omega_q) sinc(omega_q w / 2)| on the DFT grid (None without a band-limited IRF)."""
    if irf is None or not bin_width or not getattr(irf, "band_limited", False):
        return None
    q = np.arange(P)
    omega = 2 * math.pi * np.minimum(q, P - q) / (P * bin_width)
    return np.abs(irf.fourier(omega) * np.sinc(omega * bin_width / (2 * math.pi)))


def _rss(Bt, S, Lq, e_perp, lam, P) -> float:
    """||y - y_hat||^2 for one trace (Parseval): the records' part outside the codes' span
    ``e_perp`` plus ``sum (1 - f)^2 |B|^2 / S / P``, written without cancellation."""
    D = S + lam * Lq
    ok = (S > 0) & (D > 0)
    g = np.abs(Bt[ok]) ** 2 / S[ok]
    return float(e_perp + np.sum((lam * Lq[ok] / D[ok]) ** 2 * g) / P)


def _choose_lambda(Bt, S, Lq, e_perp, R, P, scale, method, sigma) -> float:
    if not np.any(Bt):
        return scale
    lo, hi = math.log(scale * 1e-14), math.log(scale * 1e8)
    if method == "discrepancy":
        # the residual the filter can reach: the in-band, in-span part (sum S > 0 terms); the
        # rest (e_perp) is left whatever lambda is
        target = e_perp + int(np.count_nonzero(S > 0)) * float(sigma) ** 2
        if _rss(Bt, S, Lq, e_perp, math.exp(lo), P) >= target:
            return math.exp(lo)
        if _rss(Bt, S, Lq, e_perp, math.exp(hi), P) <= target:
            return math.exp(hi)
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            if _rss(Bt, S, Lq, e_perp, math.exp(mid), P) < target:
                lo = mid
            else:
                hi = mid
        return math.exp(0.5 * (lo + hi))

    def gcv(loglam):
        lam = math.exp(loglam)
        D = S + lam * Lq
        tr = float(np.sum(np.where((D > 0) & (S > 0), S / np.where(D > 0, D, 1.0), 0.0)))
        return R * P * max(_rss(Bt, S, Lq, e_perp, lam, P), 0.0) / max(R * P - tr, 1e-12) ** 2

    grid = np.linspace(lo, hi, 89)
    vals = np.array([gcv(g) for g in grid])
    k = int(np.argmin(vals))
    a, b = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    res = minimize_scalar(gcv, bounds=(a, b), method="bounded", options={"xatol": 1e-4})
    return math.exp(float(res.x))
