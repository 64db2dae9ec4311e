"""Levenberg-Marquardt (scipy ``least_squares``) on the joint NLP's residuals: the paper's solver.

When to use: as the paper's method and the baseline of the benchmarks. ``jacobian="ad"`` feeds
the exact CasADi Jacobian; ``jacobian="fd"`` lets scipy difference the residuals. LM solves the
unconstrained least-squares problem (``method="lm"``) or a bounded one (``"trf"``); the NLP's
nonlinear constraints are not enforced: they are checked at the result and a violation fails
the solve. Gaussian OEM only (PEM's log-determinant and the Poisson likelihood are not sums of
squares: use IPOPT).
"""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares

from ..errors import ModelError, SolverError
from .solve import Solution

__all__ = ["solve_lm"]


def solve_lm(nlp, x0=None) -> Solution:
    """Solve with scipy ``least_squares``; return a ``Solution`` (or raise ``SolverError``)."""
    st = nlp.settings.lm
    if nlp.poisson or nlp.pem:
        raise ModelError("Levenberg-Marquardt handles the Gaussian output-error cost only; got "
                         f"likelihood={nlp.settings.cost.likelihood!r}, cost={nlp.settings.cost.cost!r}. "
                         "Use solver='ipopt' for PEM or Poisson.")
    lam = nlp.settings.cost.tikhonov
    sq = np.sqrt(2.0 * lam)
    gl = np.asarray(nlp.gloss_idx, int)
    sg = np.sqrt(2.0 * nlp.settings.cost.gloss_prior) if len(gl) else 0.0
    x0g = nlp.model.x0[gl] if len(gl) else np.zeros(0)

    def fun(x):
        parts = [nlp.residuals(x)]
        if lam > 0:
            parts.append(sq * (x - nlp.x_ref))
        if sg > 0:
            parts.append(sg * (x[gl] - x0g))
        return np.concatenate(parts)

    def jac(x):
        parts = [nlp.jacobian(x)]
        if lam > 0:
            parts.append(sq * np.eye(len(x)))
        if sg > 0:
            parts.append(sg * np.eye(len(x))[gl])
        return np.vstack(parts)

    x_init = np.clip(np.asarray(nlp.x0 if x0 is None else x0, float), nlp.lbx, nlp.ubx)
    kw = dict(xtol=st.xtol, ftol=st.ftol, gtol=st.gtol, max_nfev=st.max_nfev, x_scale=1.0)
    if st.method == "trf":
        lb = np.where(np.isfinite(nlp.lbx), nlp.lbx, -np.inf)
        ub = np.where(np.isfinite(nlp.ubx), nlp.ubx, np.inf)
        kw["bounds"] = (lb, ub)
        x_init = np.clip(x_init, lb + 1e-12 * (ub - lb), ub - 1e-12 * (ub - lb))
    t0 = time.perf_counter()
    res = least_squares(fun, x_init, jac=jac if st.jacobian == "ad" else "2-point", method=st.method, **kw)
    t_solve = time.perf_counter() - t0
    viol = nlp.constraint_violation(res.x)
    ok = bool(res.success) and res.status > 0 and viol <= 1e-6
    status = res.message if viol <= 1e-6 else f"{res.message} but constraints violated by {viol:.3g}"
    sol = Solution(np.asarray(res.x), ok, status, int(res.nfev), float(nlp.f_cost(res.x)), 0.0, t_solve,
                   solver=f"lm-{st.jacobian}",
                   info={"njev": int(res.njev or 0), "method": st.method, "jacobian": st.jacobian,
                         "constraint_violation": viol})
    if not ok and st.raise_on_failure:
        raise SolverError(f"Levenberg-Marquardt ({st.method}, {st.jacobian} Jacobian) failed: {status} "
                          f"(scipy status {res.status}). Allowed: converged with every constraint "
                          "satisfied. Try solver='ipopt' (constraints enforced) or method='trf'.",
                          status=status, stats=sol.info)
    return sol
