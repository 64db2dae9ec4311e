"""Is each cell's integration fine enough for the data's noise? Step 4d of ``fit.py``.

When to use: called by ``fit_surface`` after its last level's solves
(``SurfaceSettings.quadrature_check``); nothing else needs it.

The model integrates each node's cell by q x q sub-samples, each one Gaussian whose width holds
its sub-cell's delay spread (``SurfaceModel(subsamples=q)``); the level's q comes from a rule on
the cell's size against the response's width. That rule ignores the noise: a moment-matched cell
is still off in its first moment (the 1/d^2 and cosine weights vary across it), an error of a
fixed size, and at low noise it outgrows the std while the whitened chi^2 barely moves. Measured
on the study's seed 819 (a spherical cap, paired relay) rendered at 0.1 % noise: with q = 1 its
depths came out 0.21 mm too deep on average (rms 0.25 mm) against a std of 0.056 mm, 5 of 10 claims
beyond 4 std at chi2/dof 1.027 (passed); with q = 2, 0.049 mm (rms 0.097); with q = 3, 0.019 mm
(rms 0.079).

So the fit asks the data: the models with q and q + 1 sub-samples are linearised at the
solution, and the first-order change of the solution from one to the other, A^-1 (g_{q+1} -
g_q) (A the Gauss-Newton matrix with the prior), is taken in units of the std. When it moves a
lit node's depth or albedo by ``CONVERGED_STD`` of its std or more, the level is solved again
with q + 1 from the solution, and asked again, up to ``Q_MAX``; a change that large at ``Q_MAX``
is a reason (the fit is not converged in its own model).
"""
from __future__ import annotations

import numpy as np

from .lm import CONVERGED_STD, _free, prior_gradient
from .mask import bright_nodes
from .stdmaps import gauss_newton_matrix

__all__ = ["Q_MAX", "refine_quadrature"]

#: the most sub-samples per cell side the check raises q to (the model's cost grows as q^2)
Q_MAX = 4


def _newton(model, state, y, wgt, lam, R) -> tuple[dict, np.ndarray, np.ndarray]:
    """The float64 linearisation of ``model`` at ``state``, its Gauss-Newton matrix with the
    prior (a 1e-12 ridge) and the gradient with the prior."""
    lin = model.linearise(state, y, wgt, dtype=np.float64)
    return lin, gauss_newton_matrix(lin["H"], R, lam), prior_gradient(lin["g"], state, lam, R)


def _change_in_std(fine, coarse, state, y, wgt, lam, R, bounds, z) -> tuple[dict, dict]:
    """The first-order change of the solution from the coarser model to the finer one, at
    ``state``: A^-1 (g_fine - g_coarse) on the unknowns the finer model's Gauss-Newton step moves
    (``lm._free``), A the finer model's Gauss-Newton matrix with the prior, g the gradients of
    chi^2 / 2 (J^T W (m - y): where the models agree it is zero, whatever the state). In units
    of the finer model's (inflated) Fisher std: its largest for a lit node's depth or albedo
    (``max_std``) and for any node (``max_std_any``). Not the finer model's step alone: a solve
    that stopped with its step below its std (``tol_chi2``), or at its iteration limit, leaves a
    remaining step that is no error of the integration. The lit nodes: ``mask.bright_nodes`` with
    these std and ``z`` (the mask's rule before its significance test). Also returns the finer
    linearisation."""
    lin, A, g = _newton(fine, state, y, wgt, lam, R)
    g0 = coarse.linearise(state, y, wgt, dtype=np.float64, need_h=False)["g"]
    th = fine.pack(state)
    fi, _ = _free(fine, state, th, A, g, bounds, need_step=False)
    N = fine.N
    diff = np.zeros(th.size)
    if len(fi):
        diff[fi] = np.linalg.solve(A[np.ix_(fi, fi)], lin["g"][fi] - g0[fi])
    var = np.clip(np.diag(np.linalg.inv(A)), 0.0, None) * max(1.0, lin["chi2"] / max(y.size - th.size, 1))
    rz = np.abs(diff[:N]) / np.maximum(np.sqrt(var[:N]), 1e-300)
    rr = np.abs(diff[N:2 * N]) / np.maximum(np.sqrt(var[N:2 * N]), 1e-300)
    lit = bright_nodes(state.rho, np.sqrt(var[N:2 * N]), z)
    both = np.maximum(rz, rr)
    return {"max_std": float(both[lit].max()) if lit.any() else None, "max_std_any": float(both.max())}, lin


def refine_quadrature(state, res: dict, model, bounds, y, wgt, lam, R, make_model, make_bounds, solve,
                      q_max: int = Q_MAX, z: float = 3.0) -> dict:
    """Step 4d (module docstring) from the level's solution ``state`` (``res``) of ``model`` with
    ``bounds``; ``make_model(nodes, sub=q)``, ``make_bounds(model)`` and ``solve(model, bounds,
    state, lin0)`` as the level's own; ``z`` the mask's significance (``SurfaceSettings.mask_z``)
    for its lit nodes (``mask.bright_nodes``).

    Returns dict ``info`` (a list of checks: q, q + 1, the change's largest on a lit node in std
    ``max_std``, whether the level was solved again and that solve's status, iterations and
    F), ``converged`` (False when the check at ``q_max`` still moves a lit node by
    ``CONVERGED_STD`` or more), the final ``model``, ``bounds``, ``res``, and ``solves`` (each
    re-solve's result, in order)."""
    checks, solves = [], []
    converged = True
    while True:
        q = int(model.sub)
        nodes = model.onodes if model.K else None
        m2 = make_model(nodes, sub=q + 1, **({"extent": True} if model.extent else {}))
        b2 = make_bounds(m2)
        rs, lin = _change_in_std(m2, model, state, y, wgt, lam, R, b2, z)
        worst = rs["max_std"]
        rec = {"q": q, "q_next": q + 1} | rs
        if worst is None or worst < CONVERGED_STD:
            checks.append(rec | {"solved": False})
            break
        if q + 1 > q_max:
            checks.append(rec | {"solved": False})
            converged = False
            break
        out = solve(m2, b2, state, lin)
        checks.append(rec | {"solved": True, "status": out["status"], "iterations": out["iterations"],
                             "f": float(out["f"]), "f_before": float(res["f"])})
        model, bounds, res, state = m2, b2, out, out["state"]
        solves.append(out)
    return {"info": checks, "converged": converged, "model": model, "bounds": bounds, "res": res,
            "solves": solves}
