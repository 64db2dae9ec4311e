"""Levenberg-Marquardt (scipy ``least_squares``) on the same residuals, the paper's method.

When to use: as the paper's solver and as the baseline of the benchmarks. ``jacobian="ad"``
feeds the exact CasADi Jacobian; ``jacobian="fd"`` lets scipy difference the residuals (what a
MATLAB ``lsqnonlin`` / scipy user gets by default). LM solves the unconstrained least-squares
problem (``method="lm"``) or a bounded one (``"trf"``); the NLP's nonlinear constraints
(energy, stability, hidden distances) are not enforced by LM: they are checked at the result and
a violation fails the solve. Gaussian OEM only (PEM's log-determinant and the Poisson likelihood
are not sums of squares: use IPOPT).
"""
from __future__ import annotations

import time

import numpy as np
from scipy.optimize import least_squares

from ..errors import ModelError, SolverError
from .nlp import ReflectanceNLP


def solve_lm(nlp: ReflectanceNLP, x0=None):
    """Solve with scipy ``least_squares``; return an ``Estimate`` (or raise ``SolverError``)."""
    from .result import Estimate

    st = nlp.settings.lm
    if nlp.poisson or nlp.pem:
        raise ModelError("Levenberg-Marquardt handles the Gaussian output-error cost only; got "
                         f"likelihood={nlp.settings.cost.likelihood!r}, cost={nlp.settings.cost.cost!r}. "
                         "Use solver='ipopt' for PEM or Poisson.")
    lam = nlp.settings.cost.tikhonov
    sq = np.sqrt(2.0 * lam)
    xref = nlp.x_ref

    gl = np.asarray(nlp.gloss_idx, int)
    sg = np.sqrt(2.0 * nlp.settings.cost.gloss_prior) if len(gl) else 0.0
    x0g = nlp.model.x0[gl] if len(gl) else np.zeros(0)

    def fun(x):
        parts = [nlp.residuals(x)]
        if lam > 0:
            parts.append(sq * (x - xref))
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
    res = least_squares(fun, x_init, jac=jac if st.jacobian == "ad" else "2-point",
                        method=st.method, **kw)
    t_solve = time.perf_counter() - t0
    viol = nlp.constraint_violation(res.x)
    ok = bool(res.success) and res.status > 0 and viol <= 1e-6
    status = res.message if viol <= 1e-6 else f"{res.message} but constraints violated by {viol:.3g}"
    info = {"status": status, "iterations": int(res.nfev), "njev": int(res.njev or 0),
            "success": ok, "method": st.method, "jacobian": st.jacobian, "build_time_s": 0.0,
            "solve_time_s": t_solve, "cost": float(nlp.f_cost(res.x)), "constraint_violation": viol}
    est = Estimate.from_solution(nlp, res.x, solver=f"lm-{st.jacobian}", info=info)
    if not ok and st.raise_on_failure:
        raise SolverError(f"Levenberg-Marquardt ({st.method}, {st.jacobian} Jacobian) failed: {status} "
                          f"(scipy status {res.status}). Allowed: converged with every constraint "
                          "satisfied. Try solver='ipopt' (constraints enforced) or method='trf'.",
                          status=status, stats=info)
    return est
