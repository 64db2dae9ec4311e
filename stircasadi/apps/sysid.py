"""System identification: the scene's LTI model from input/output records (FIR least squares).

When to use
-----------
The paper's framing (section 4.1): light transport is a MIMO LTI system, so its input/output
behaviour can be identified from records of *any* known illumination, not only from impulses:
several patches driven at once by different codes, transient (from rest) and non-periodic.
The identified model is the STIR itself, as a finite impulse response (FIR) per (input patch,
observed patch), and it predicts the response to inputs it was not identified from (held-out
records). Deconvolving one periodic code per record is ``stircasadi.apps.deconvolve``.

Model and estimator (stated: FIR least squares with ridge regularisation, not a state-space
realisation)
------------
With inputs ``u_i[t]`` (energy aimed at illuminated patch i at the instant t * bin_width) and
outputs ``y_j[k]`` on the STIR's grid (``stircasadi.apps.deconvolve`` explains the axes),

    y_j[k] = sum_i sum_{m=0}^{L-1} h_ij[m] u_i[k - m] + e_j[k],      e ~ N(0, sigma^2),

stacked over records and time into ``y_j = Phi c_j`` (Phi: (records x T) x (inputs x L), shared
by every output). With the SVD ``Phi = U s V^T``:

    c_j = V diag(s / (s^2 + lambda)) U^T y_j,

lambda per output by generalised cross-validation, sigma from the residual
(``||r||^2 / (N - sum f)``, ``f = s^2 / (s^2 + lambda)``). ``h[i, j, :]`` is returned in the STIR's
axis order. ``validate`` predicts held-out records and returns the whitened residual's
chi^2 / dof (about 1 when the model reproduces them to the noise).

Neglects: noise that is not white; responses longer than L taps (they appear as misfit); the
model order of a minimal state-space realisation (an ERA/Ho-Kalman step on ``h`` would give one).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from ..errors import CodeError

__all__ = ["FIRModel", "identify_fir", "validate", "predict"]


@dataclass
class FIRModel:
    """An identified MIMO FIR model: ``h`` (n_in, n_out, L) like ``stir[i, j, k]``, with the
    per-output ``lam``, ``sigma`` and the coefficient ``std`` (n_in, n_out, L)."""

    h: np.ndarray
    lam: np.ndarray
    sigma: np.ndarray
    std: np.ndarray
    metadata: dict = field(default_factory=dict)
    #: per output, A_j with coefficient covariance sigma_j^2 A_j A_j^T
    cov_factor: np.ndarray | None = None


def _check(inputs, outputs):
    u = np.asarray(inputs, float)
    y = np.asarray(outputs, float)
    if u.ndim == 2:
        u = u[None]
    if y.ndim == 2:
        y = y[None]
    if u.ndim != 3 or y.ndim != 3 or u.shape[0] != y.shape[0]:
        raise CodeError(f"inputs must be (n_records, n_inputs, T_in) and outputs (n_records, n_outputs, T) "
                        f"with the same number of records; got {u.shape} and {y.shape}.")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        raise CodeError("inputs and outputs must be finite (no NaN or inf).")
    return u, y


def _regressors(u: np.ndarray, T: int, L: int) -> np.ndarray:
    """Phi (R T, n_in L): row (r, k), column (i, m) holds u[r, i, k - m] (0 before t = 0)."""
    R, n_in, Tu = u.shape
    up = np.zeros((R, n_in, T))
    up[:, :, :min(T, Tu)] = u[:, :, :T]
    Phi = np.zeros((R, T, n_in, L))
    for m in range(L):
        Phi[:, m:, :, m] = np.transpose(up[:, :, :T - m], (0, 2, 1))
    return Phi.reshape(R * T, n_in * L)


def identify_fir(inputs, outputs, n_taps: int, sigma: float | None = None) -> FIRModel:
    """Identify ``h`` (n_in, n_out, n_taps) from records (module doc).

    inputs : (n_records, n_inputs, T_in) energies at the bin instants from t = 0.
    outputs : (n_records, n_outputs, T) the recorded responses on the STIR's grid.
    sigma : noise std of the outputs (estimated per output when None).
    """
    u, y = _check(inputs, outputs)
    R, n_out, T = y.shape
    n_in = u.shape[1]
    if not (isinstance(n_taps, (int, np.integer)) and 1 <= n_taps <= T):
        raise CodeError(f"n_taps must be an integer in 1..{T} (the record length); got {n_taps!r}.")
    Phi = _regressors(u, T, int(n_taps))
    N, p = Phi.shape
    if N < p:
        raise CodeError(f"{N} output samples per observed patch cannot identify {p} FIR taps "
                        f"({n_in} inputs x {n_taps}); record longer or more records.")
    Us, s, Vt = np.linalg.svd(Phi, full_matrices=False)
    if not s.size or s[0] <= 0:
        raise CodeError("The inputs are all zero: nothing can be identified.")
    if s[-1] / s[0] < 1e-12:
        raise CodeError(f"The inputs do not excite every tap (condition number {s[0] / max(s[-1], 1e-300):.3g}): "
                        "drive each patch with a persistently exciting code (an MLS or a random binary "
                        "sequence), different for patches driven at once.")
    Y = y.transpose(1, 0, 2).reshape(n_out, N)              # (n_out, N)
    beta = Y @ Us                                           # (n_out, p)
    perp = np.maximum(np.sum(Y ** 2, axis=1) - np.sum(beta ** 2, axis=1), 0.0)
    s2 = s ** 2
    lam = np.array([_gcv_lambda(beta[j], s2, perp[j], N) for j in range(n_out)])
    f = s2[None, :] / (s2[None, :] + lam[:, None])
    C = (beta * (s[None, :] / (s2[None, :] + lam[:, None]))) @ Vt   # (n_out, p)
    rss = perp + np.sum(((1 - f) * beta) ** 2, axis=1)
    sig = (np.sqrt(rss / np.maximum(N - f.sum(axis=1), 1.0)) if sigma is None
           else np.full(n_out, float(sigma)))
    # coefficient covariance of a ridge estimate: sigma^2 V diag(s^2 / (s^2 + lam)^2) V^T
    cstd = np.sqrt(np.einsum("jk,kp->jp", s2[None, :] / (s2[None, :] + lam[:, None]) ** 2, Vt ** 2)) * sig[:, None]
    h = C.reshape(n_out, n_in, n_taps).transpose(1, 0, 2)
    std = cstd.reshape(n_out, n_in, n_taps).transpose(1, 0, 2)
    Afac = np.einsum("pk,jk->jpk", Vt.T, s[None, :] / (s2[None, :] + lam[:, None]))
    return FIRModel(h=h, lam=lam, sigma=sig, std=std, cov_factor=Afac,
                    metadata={"n_records": R, "n_samples": N, "n_params_per_output": p,
                              "condition": float(s[0] / s[-1]), "estimator": "FIR ridge, GCV"})


def predict(model: FIRModel, inputs, T: int) -> np.ndarray:
    """Outputs (n_records, n_out, T) the model gives for ``inputs`` (n_records, n_in, T_in)."""
    u = np.asarray(inputs, float)
    if u.ndim == 2:
        u = u[None]
    n_in, n_out, L = model.h.shape
    if u.shape[1] != n_in:
        raise CodeError(f"The model has {n_in} inputs; the records drive {u.shape[1]}.")
    Phi = _regressors(u, T, L)
    C = model.h.transpose(1, 0, 2).reshape(n_out, n_in * L)
    return (Phi @ C.T).reshape(u.shape[0], T, n_out).transpose(0, 2, 1)


def validate(model: FIRModel, inputs, outputs, sigma: float | None = None) -> dict:
    """How well the model reproduces held-out records: the whitened residual's chi^2 / dof and
    the value expected if the model is right, ``1 + mean(phi^T Cov(c) phi) / sigma^2`` (the
    held-out noise plus the identified coefficients' own error), and the relative RMS error.
    ``sigma`` defaults to the model's."""
    u, y = _check(inputs, outputs)
    T = y.shape[-1]
    yp = predict(model, u, T)
    sig = model.sigma if sigma is None else np.full(y.shape[1], float(sigma))
    r = (y - yp) / sig[None, :, None]
    expected = 1.0
    if model.cov_factor is not None:
        Phi = _regressors(u, T, model.h.shape[2])
        lev = np.array([np.mean(np.sum((Phi @ model.cov_factor[j]) ** 2, axis=1)) * model.sigma[j] ** 2
                        / sig[j] ** 2 for j in range(y.shape[1])])
        expected = float(1.0 + np.mean(lev))
    return {"chi2_dof": float(np.mean(r ** 2)), "expected_chi2_dof": expected,
            "rel_rms": float(np.sqrt(np.mean((y - yp) ** 2)) / max(np.sqrt(np.mean(y ** 2)), 1e-300)),
            "n": int(r.size)}


def _gcv_lambda(b, s2, perp, N) -> float:
    def gcv(ll):
        lam = math.exp(ll)
        f = s2 / (s2 + lam)
        rss = perp + np.sum(((1 - f) * b) ** 2)
        return N * rss / max(N - f.sum(), 1e-12) ** 2
    lo, hi = math.log(s2[0] * 1e-16), math.log(s2[0] * 1e2)
    grid = np.linspace(lo, hi, 73)
    k = int(np.argmin([gcv(g) for g in grid]))
    res = minimize_scalar(gcv, bounds=(grid[max(k - 1, 0)], grid[min(k + 1, 72)]), method="bounded",
                          options={"xatol": 1e-4})
    return math.exp(float(res.x))
