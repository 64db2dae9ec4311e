"""All-bounce (or K-bounce) transport in the frequency domain: the resolvent of the delay network.

When to use: the full STIR with every bounce (interreflections to convergence), fast for
hundreds of patches: per frequency one complex M x M solve. Needs a band-limited sensor
(Gaussian impulse response) in exact-delay mode; in integer-delay mode any sensor works (the
DFT of whole-bin delays is exact).

Equation: with the network of ``stircasadi.transport.system`` and F[f](w) = int f(t) e^{-iwt} dt,

    Y(w) = O(w) (I - T(w))^{-1} S(w),     X(w)_rc = sum_terms coef e^{-i w length}        (all)
    Y_K(w) = sum_{n=1..K} O(w) T(w)^{n-1} S(w)                                             (K)

and bin k (left edge t_k) of the STIR is the band-limited inverse transform

    y_k = 1/P sum_m Y(w_m) G(w_m) e^{i w_m t_k},  w_m = 2 pi m / P,
    G(w) = IRF(w) (e^{i w dt} - 1) / (i w)        (the impulse response integrated over a bin).

Truncation error, bounded and reported:
* band: frequencies are kept while |IRF(w)| > 1e-15 (Gaussian), so the band error is below
  1e-15 of the signal (frequencies past Nyquist fold onto the DFT grid, exactly);
* time aliasing: the sum is periodic with period P = N dt. Paths arriving after start + P wrap
  around. P is chosen so every path with fewer than b bounces arrives inside the period, where
  the energy of all paths with >= b bounces, E_{>=b} = 1^T O T0^{b-1} (I - T0)^{-1} S 1 (exact,
  at w = 0), is below ``tail_tol`` of the total. The achieved bound is reported as
  ``alias_energy_bound_rel`` (an upper bound on the summed absolute error of the wrapped part).
The spectral radius of T0 must be < 1 (no energy created); otherwise a TransportError is raised.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft
import scipy.linalg as sla
from scipy.sparse.linalg import spsolve

from ..errors import TransportError
from ..progress import progress
from ..timegrid import TimeGrid
from .deposit import bin_integer_samples, kernel_support
from .system import TransportSystem


def _phases(omega: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """``exp(-i omega_f l_t)`` (F, n_terms). On a uniform frequency chunk the rows follow by
    repeated multiplication with ``exp(-i d_omega l)`` from an exact first row (relative drift
    below F * 1e-16, re-anchored every chunk), which is several times cheaper than ``exp``."""
    F = len(omega)
    if F < 3 or not np.allclose(np.diff(omega), omega[1] - omega[0], rtol=1e-12, atol=0):
        return np.exp(-1j * omega[:, None] * lengths[None, :])
    out = np.empty((F, len(lengths)), complex)
    out[0] = np.exp(-1j * omega[0] * lengths)
    step = np.exp(-1j * (omega[1] - omega[0]) * lengths)
    for f in range(1, F):
        np.multiply(out[f - 1], step, out=out[f])
    return out


class _DenseBuilder:
    """Scatter terms (row, col, coef, length) into dense complex matrices for many frequencies.

    ``single_row_terms`` is set when every row has exactly one term (a Lambertian observation or
    source map): the matrix product then reduces to a gather, which ``apply_left`` uses.
    """

    def __init__(self, terms, shape):
        r, c, v, l = terms
        self.shape = shape
        self.single_row_terms = len(r) == shape[0] and np.array_equal(np.sort(r), np.arange(shape[0]))
        if self.single_row_terms:
            o = np.argsort(r)
            self.g_col, self.g_v, self.g_l = c[o], v[o], l[o]
        flat = r * shape[1] + c
        order = np.argsort(flat, kind="stable")
        flat, v, l = flat[order], v[order], l[order]
        first = np.ones(len(flat), bool)
        first[1:] = flat[1:] != flat[:-1]
        self.f_idx, self.f_v, self.f_l = flat[first], v[first], l[first]
        self.d_idx, self.d_v, self.d_l = flat[~first], v[~first], l[~first]

    def at(self, omega: np.ndarray) -> np.ndarray:
        F = len(omega)
        out = np.zeros((F, self.shape[0] * self.shape[1]), complex)
        out[:, self.f_idx] = self.f_v[None, :] * _phases(omega, self.f_l)
        if len(self.d_idx):
            vals = self.d_v[None, :] * _phases(omega, self.d_l)
            for f in range(F):
                np.add.at(out[f], self.d_idx, vals[f])
        return out.reshape(F, *self.shape)

    def apply_left(self, omega: np.ndarray, X: np.ndarray) -> np.ndarray:
        """``M(omega) @ X`` for a batch X (F, shape[1], k)."""
        if self.single_row_terms:
            ph = self.g_v[None, :] * _phases(omega, self.g_l)
            return ph[:, :, None] * X[:, self.g_col, :]
        return self.at(omega) @ X


def bounce_energies(system: TransportSystem, n_max: int) -> tuple[np.ndarray, float]:
    """Exact time-integrated energy (summed over the STIR) of bounces 1..n_max, and the total."""
    S0, T0, O0 = system.steady_matrices()
    v = S0 @ np.ones(system.n_ill)
    ones_o = np.ones(system.n_obs) @ O0
    e = np.empty(n_max)
    for n in range(n_max):
        e[n] = ones_o @ v
        v = T0 @ v
    total_v = spsolve((_identity(system.n_nodes) - T0).tocsc(), S0 @ np.ones(system.n_ill))
    total = float(ones_o @ np.atleast_1d(total_v))
    return e, total


def _identity(n):
    from scipy import sparse
    return sparse.identity(n, format="csr")


def spectral_radius(system: TransportSystem) -> float:
    """Spectral radius of the non-negative transfer matrix T0 (< 1 for a physical scene)."""
    _, T0, _ = system.steady_matrices()
    n = T0.shape[0]
    if n == 0 or T0.nnz == 0:
        return 0.0
    if n <= 600:
        return float(np.max(np.abs(np.linalg.eigvals(T0.toarray()))))
    from scipy.sparse.linalg import eigs
    return float(np.abs(eigs(T0, k=1, which="LM", return_eigenvectors=False)[0]))


def plan_period(system: TransportSystem, grid: TimeGrid, irf, bounces: int | None,
                tail_tol: float, max_factor: int) -> tuple[int, dict]:
    """Choose the FFT length N (period N*dt) and report the aliasing bound."""
    w = grid.bin_width
    lo_s, hi_s = kernel_support(irf, w, system.delay_mode == "integer")
    t_lo, _ = system.arrival_window(1)
    info: dict = {}
    if bounces is not None:
        _, t_hi = system.arrival_window(bounces)
        info["alias_energy_bound_rel"] = 0.0
    else:
        rho = spectral_radius(system)
        info["spectral_radius"] = rho
        if rho >= 1.0:
            raise TransportError(f"The scene's transfer operator has spectral radius {rho:.4g} >= 1: "
                                 "interreflections would create energy (albedos too high for patches "
                                 "this large and close). Lower albedos or subdivide the patches.")
        n_cap = 10_000
        e, total = bounce_energies(system, min(n_cap, 4096))
        tail = total - np.cumsum(np.concatenate([[0.0], e]))  # tail[b] = energy of bounces > b
        tail = np.maximum(tail, 0.0)
        t_max_cap = grid.start + max_factor * grid.n_bins * w
        b_ok = 1
        for b in range(1, len(e) + 1):
            if system.arrival_window(b)[1] + hi_s > t_max_cap:
                break
            b_ok = b
            if total <= 0 or tail[b] <= tail_tol * total:
                break
        _, t_hi = system.arrival_window(b_ok)
        info["alias_energy_bound_rel"] = float(tail[b_ok] / total) if total > 0 else 0.0
        info["bounces_inside_period"] = b_ok
        info["total_energy"] = total
    span_hi = max(t_hi + hi_s, grid.end)
    span_lo = min(grid.start, t_lo + lo_s)
    n = int(math.ceil((span_hi - span_lo) / w)) + 2
    n = max(n, grid.n_bins)
    if system.delay_mode == "integer":
        # the sample grid starts at t=0 in integer mode: cover [0, span_hi]
        n = max(n, int(math.ceil(span_hi / w)) + 2)
    n = sfft.next_fast_len(n, real=True)
    info["fft_length"] = n
    return n, info


def frequency_solve(system: TransportSystem, grid: TimeGrid, irf, bounces: int | None = None,
                    tail_tol: float = 1e-10, max_factor: int = 16, chunk_bytes: float = 2.5e8,
                    block_bytes: float = 4e9, out=None):
    """STIR (n_ill, n_obs, n_bins) by the resolvent (bounces=None) or its K-term Neumann sum.

    Memory: when the spectrum of every pulse would exceed ``block_bytes``, it is computed
    frequency chunk by frequency chunk (one LU per frequency, O(M^2) each) into a temporary
    file, and turned into time traces pulse block by pulse block; with ``out`` (any array-like
    of the STIR's shape: an ``np.memmap`` or an h5py dataset) each block is written there as it
    is finished. The working memory is then O(M^2 + block * M * T), never the whole STIR.
    """
    integer = system.delay_mode == "integer"
    if not integer and not getattr(irf, "band_limited", False):
        raise TransportError(
            f"The frequency-domain method with exact delays needs a band-limited impulse response "
            f"(GaussianIRF); the sensor has '{irf.describe()}'. Use method='bounces' (exact path "
            "sums, any sensor), delay_mode='integer', or give the sensor a GaussianIRF.")
    N, info = plan_period(system, grid, irf, bounces, tail_tol, max_factor)
    w = grid.bin_width
    P = N * w
    m_max = N // 2 if integer else int(math.ceil(irf.band_limit() * P / (2 * math.pi)))
    info["n_frequencies"] = m_max + 1
    omega = 2 * math.pi * np.arange(m_max + 1) / P
    nu, ni, no = system.n_nodes, system.n_ill, system.n_obs
    shape = (ni, no, grid.n_bins)
    if out is None:
        out = np.zeros(shape)
    elif tuple(out.shape) != shape:
        raise TransportError(f"out must have the STIR's shape {shape}; got {tuple(out.shape)}.")
    per_pulse = no * (16 * (m_max + 1) + 8 * N + 16 * N + 8 * grid.n_bins)
    block = int(max(1, min(ni, block_bytes // max(per_pulse, 1))))
    info["pulse_blocks"] = int(math.ceil(ni / block))
    Tb, Ob = _DenseBuilder(system.T, (nu, nu)), _DenseBuilder(system.O, (no, nu))
    G = None
    if not integer:
        G = np.empty(len(omega), complex)
        G[0] = w
        om = omega[1:]
        G[1:] = irf.fourier(om) * (np.exp(1j * om * w) - 1.0) / (1j * om)
        G *= np.exp(1j * omega * grid.start)
    n_rows = N // 2 + 1 if (integer or m_max <= N // 2) else len(omega)
    Sb = _DenseBuilder(system.S, (nu, ni))
    if block >= ni:
        spec = _spectrum(Sb, Tb, Ob, omega, bounces, nu, ni, no, chunk_bytes, n_rows)
        out[...] = _to_time(spec, grid, irf, N, P, m_max, G, integer)
        return out, info
    import os
    import tempfile

    with tempfile.TemporaryDirectory(prefix="stircasadi-spec-") as tmp:
        spec_all = np.lib.format.open_memmap(os.path.join(tmp, "spectrum.npy"), mode="w+",
                                             dtype=complex, shape=(n_rows, ni, no))
        _spectrum(Sb, Tb, Ob, omega, bounces, nu, ni, no, chunk_bytes, n_rows, out=spec_all)
        for c0 in progress(range(0, ni, block), desc="pulse blocks", unit="block"):
            c1 = min(ni, c0 + block)
            out[c0:c1] = _to_time(np.array(spec_all[:, c0:c1]), grid, irf, N, P, m_max, G, integer)
        del spec_all
    return out, info


def _spectrum(Sb, Tb, Ob, omega, bounces, nu, ni, no, chunk_bytes, n_rows=None, out=None):
    """Y(w) for every frequency, shape (n_rows >= F, n_ill, n_obs); rows past F are zero (the
    padding up to the inverse FFT's length, allocated once). Written into ``out`` if given."""
    spec = np.zeros((max(n_rows or 0, len(omega)), ni, no), complex) if out is None else out
    per_freq = 16 * (3 * nu * nu + 2 * nu * ni + no * nu + no * ni)
    fchunk = max(1, int(chunk_bytes // max(per_freq, 1)))
    diag = np.arange(nu)
    bar = progress(total=len(omega), desc="frequencies", unit="freq")
    for s in range(0, len(omega), fchunk):
        bar.update(min(fchunk, len(omega) - s))
        om = omega[s:s + fchunk]
        Sw, Tw = Sb.at(om), Tb.at(om)
        if bounces is None:
            Tw *= -1.0
            Tw[:, diag, diag] += 1.0  # I - T(w), in place
            X = np.empty_like(Sw)
            for f in range(len(om)):  # LAPACK per frequency: faster than numpy's batched solve here
                X[f] = sla.lu_solve(sla.lu_factor(Tw[f], overwrite_a=True, check_finite=False),
                                    Sw[f], check_finite=False)
            Y = Ob.apply_left(om, X)
        else:
            V = Sw
            Y = Ob.apply_left(om, V)
            for _ in range(bounces - 1):
                V = Tw @ V
                Y += Ob.apply_left(om, V)
        spec[s:s + len(om)] = np.transpose(Y, (0, 2, 1))
    bar.close()
    return spec


def _to_time(spec, grid, irf, N, P, m_max, G, integer):
    """Band-limited inverse transform of Y(w) (F, a, b) to binned time (a, b, n_bins)."""
    if integer:
        # samples at t = n*w (n = 0..N-1), then bins k = n - start/w, then the discrete IRF:
        # the DFT of whole-bin delays is exact, irfft returns at sample n the summed amplitude
        # of the paths whose delay is n bins (no aliasing: N covers every path)
        y = np.moveaxis(sfft.irfft(spec, n=N, axis=0), 0, -1)
        return bin_integer_samples(y, grid, irf)
    spec[:len(G)] *= G[:, None, None]
    if m_max <= N // 2:
        # Hermitian: y_k = (Z_0 + 2 Re sum_{m>=1} Z_m e^{2 pi i m k / N}) / P  == irfft * N / P
        # (spec already holds N // 2 + 1 rows, zero past m_max)
        y = sfft.irfft(spec, n=N, axis=0, overwrite_x=True)[:grid.n_bins] * (N / P)
    else:  # frequencies beyond Nyquist fold onto m mod N (a narrow impulse response)
        F = np.zeros((N,) + spec.shape[1:], complex)
        for m in range(1, m_max + 1):
            F[m % N] += spec[m]
        y = (spec[:1].real + 2.0 * (sfft.ifft(F, axis=0) * N).real)[:grid.n_bins] / P
    return np.moveaxis(y, 0, -1)
