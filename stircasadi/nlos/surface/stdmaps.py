"""The std maps of a fitted surface, and what they rest on under a smoothness prior (step 5 of
``fit.py``'s docstring).

When to use: called by ``fit_surface`` once its last level is solved; nothing else needs it.

``std_maps`` turns a covariance of the unknowns (depths, albedos, then the response's and
background's) into one-sigma std of depth, albedo and the normal's components (the normals
linearised through the depth gradients), inflated by sqrt(chi2/dof) when above 1.

Under a prior (weight lam > 0, operator R) two covariances are at hand at the solution: the
posterior's (H + lam R)^-1 and the data's own Fisher bound H^-1 (H = J^T W J). The posterior's std
are narrower, and they hold the estimate's scatter about its mean, not the bias the prior adds to
that mean: on the seeded study's scenes 1300-1323 under ``prior="auto"`` (the posterior's std, edge
nodes widened) 3 of 24 scenes were SILENT-WRONG, errors up to 3.9 of those std, neighbouring
columns of a square trading albedo at 2.1-2.3 std (seed 1314). The data's std (1.7-3.2x the
posterior's at the median over the mask on 1305 and 1314, measured) do not rely on the prior being
true: the regularised estimate's own noise covariance (H + lam R)^-1 H (H + lam R)^-1 is narrower
than either, and its bias, -(H + lam R)^-1 lam R x, is what the prior's pull leaves; the data's
bound is the std an estimate of the same unknowns without the prior would have. So the maps of a
fit under a prior are the data's by default (``SurfaceSettings.claims_under_prior="data"``;
"posterior" for a user who takes the prior as knowledge of the scene). The fit's checks (the
remaining step, the depth step, the mask's significance) read the posterior's either way.

Neglects: the covariance is the Gauss-Newton one at the solution (the model's curvature beyond
its Jacobian, and the bias of a nonlinear estimate, are not in it).
"""
from __future__ import annotations

import numpy as np

from .grid import DepthGrid, normal_std

__all__ = ["CLAIMS", "std_maps", "gauss_newton_matrix", "data_covariance"]

#: what a fit's std maps rest on under a prior (``SurfaceSettings.claims_under_prior``)
CLAIMS = ("data", "posterior")


def gauss_newton_matrix(H: np.ndarray, R=None, lam: float = 0.0) -> np.ndarray:
    """A = H + lam R (R over the first R.shape[0] unknowns, the prior's) plus a ridge of 1e-12 of
    A's mean diagonal, so unknowns the data do not see, e.g. the depth of a node with zero albedo,
    get a very large but finite variance in A^-1; ``H`` is not changed."""
    A = np.array(H, dtype=float, copy=True)
    n = A.shape[0]
    if R is not None:
        M = R.shape[0]
        A[:M, :M] += lam * R
    A += (1e-12 * float(np.trace(A)) / n) * np.eye(n)
    return A


def data_covariance(H: np.ndarray) -> np.ndarray:
    """The data's own Fisher bound H^-1 (with the same relative ridge as the posterior's)."""
    return np.linalg.inv(gauss_newton_matrix(H))


def std_maps(grid: DepthGrid, C: np.ndarray, infl: float, z: np.ndarray, glob=()):
    """(depth std (N,), albedo std (N,), normal std (N, 3), {global name: std}) from the
    covariance ``C`` of (depths, albedos, globals in the order ``glob``) at depths ``z``, each
    variance times ``infl`` (max(1, chi2/dof))."""
    N = grid.n
    Cz = C[:N, :N] * infl
    z_std = np.sqrt(np.maximum(np.diag(Cz), 0))
    rho_std = np.sqrt(np.maximum(np.diag(C[N:2 * N, N:2 * N]) * infl, 0))
    gstd = {k: float(np.sqrt(max(C[2 * N + i, 2 * N + i] * infl, 0))) for i, k in enumerate(glob)}
    Gx, Gy = grid.gradient_ops()
    gx, gy = Gx @ z, Gy @ z
    GxC, GyC = np.asarray(Gx @ Cz), np.asarray(Gy @ Cz)
    vxx = np.asarray((Gx.multiply(GxC)).sum(axis=1)).ravel()
    vyy = np.asarray((Gy.multiply(GyC)).sum(axis=1)).ravel()
    vxy = np.asarray((Gy.multiply(GxC)).sum(axis=1)).ravel()
    return z_std, rho_std, normal_std(grid, gx, gy, vxx, vyy, vxy), gstd
