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
from ..progress import get_logger
from .budget import WALL_TIME_STATUS
from .solve import Solution

log = get_logger(__name__)

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


def solve_sparse_lm(nlp, x0=None, max_iter: int = 100, tol: float = 1e-6) -> Solution:
    """Levenberg-Marquardt on the sparse Jacobian, for models too large for IPOPT's exact Hessian.

    Minimises 1/2 ||r(x)||^2 + the NLP's regularisers that are sums of squares (the weak prior,
    the flatness prior, Tikhonov and the gloss prior) over the affine set of the linear equality
    constraints (the gauge: x = x0 + Z y) inside the bounds (each step is projected on them).
    Step: (Z^T (J^T J + P) Z + lambda D) dy = -Z^T g with J^T J formed sparsely (n_x x n_x
    dense, cheap for n_x ~ 1e3 even when J has 1e7 entries); lambda = 0 (Gauss-Newton with a
    backtracking line search) while that lowers the cost, raised tenfold while it does not. Converged when the largest
    gradient component is below ``tol`` times its curvature's square root (the same
    "fraction of one std" IPOPT's curvature-scaled tolerance means), or the cost stops moving.
    Nonlinear inequality constraints (stability, Phong energy) are checked at the end: a
    violation fails the solve."""
    import casadi as ca

    from .uncertainty import equality_null_space, prior_std_x

    t0 = time.perf_counter()
    n = nlp.n_x
    x = np.clip(np.asarray(nlp.x0 if x0 is None else x0, float), nlp.lbx, nlp.ubx)
    xs0 = nlp.x0.copy()
    ps = prior_std_x(nlp) if nlp.settings.cost.weak_prior else np.full(n, np.inf)
    wp = np.where(np.isfinite(ps), 1.0 / ps, 0.0)
    lam_t = nlp.settings.cost.tikhonov
    gl = np.asarray(nlp.gloss_idx, int)
    sg = np.sqrt(2.0 * nlp.settings.cost.gloss_prior) if len(gl) else 0.0
    Z = equality_null_space(nlp, x)
    fixed = nlp.lbx == nlp.ubx
    Z[fixed] = 0.0

    def parts(x):
        r = nlp.residuals(x)
        rp = [wp * (x - xs0)]
        if nlp.r_prior is not None:
            rp.append(np.asarray(ca.Function("rp", [nlp.xx], [nlp.r_prior])(x)).ravel())
        if lam_t > 0:
            rp.append(np.sqrt(2 * lam_t) * (x - nlp.x_ref))
        if sg > 0:
            rp.append(sg * (x[gl] - nlp.model.x0[gl]))
        return r, np.concatenate(rp)

    def cost(x):
        r, rp = parts(x)
        return 0.5 * (float(r @ r) + nlp.fold_const + float(rp @ rp))

    def normal_eq(x):
        r, rp = parts(x)
        J = nlp.jacobian_sparse(x)
        H = np.asarray((J.T @ J).todense())
        g = np.asarray(J.T @ r).ravel()
        H[np.diag_indices(n)] += wp ** 2
        g += wp ** 2 * (x - xs0)
        if nlp.r_prior is not None:
            Jp = nlp.prior_jacobian(x)
            H += np.asarray((Jp.T @ Jp).todense())
            g += np.asarray(Jp.T @ np.asarray(ca.Function("rp", [nlp.xx], [nlp.r_prior])(x)).ravel()).ravel()
        if lam_t > 0:
            H[np.diag_indices(n)] += 2 * lam_t
            g += 2 * lam_t * (x - nlp.x_ref)
        if sg > 0:
            H[gl, gl] += sg ** 2
            g[gl] += sg ** 2 * (x[gl] - nlp.model.x0[gl])
        return H, g

    f = cost(x)
    f_prev, small = f, 0
    lam = 0.0
    status, it = "Maximum_Iterations_Exceeded", 0
    budget = getattr(nlp, "budget", None)
    for it in range(1, max_iter + 1):
        if budget is not None and budget.expired():
            status = WALL_TIME_STATUS
            break
        H, g = normal_eq(x)
        Hz, gz = Z.T @ H @ Z, Z.T @ g
        d = np.sqrt(np.maximum(np.diag(Hz), 1e-300))
        if np.max(np.abs(gz) / d) < tol:
            status = "Solve_Succeeded"
            break
        Hn, gn = Hz / np.outer(d, d), gz / d   # Jacobi-scaled: unit diagonal
        improved = False
        # a Gauss-Newton step with a backtracking line search first (the damped step crawls when
        # the scaled information spans many decades), Levenberg-Marquardt damping if that fails
        for lam_try in [lam] + [max(lam, 1e-6) * 10.0 ** k for k in range(1, 13)]:
            try:
                dy = -np.linalg.solve(Hn + (lam_try + 1e-13) * np.eye(len(d)), gn) / d
            except np.linalg.LinAlgError:
                continue
            t = 1.0
            for _ in range(6 if lam_try == lam else 1):
                xn = np.clip(x + t * (Z @ dy), nlp.lbx, nlp.ubx)
                fn = cost(xn)
                if np.isfinite(fn) and fn <= f:
                    improved = True
                    break
                t *= 0.25
            if improved:
                rel = (f - fn) / max(abs(f), 1e-300)
                x, f = xn, fn
                lam = 0.0 if lam_try == lam and t == 1.0 else lam_try / 10.0
                break
        if not improved:
            status = "Solved_To_Acceptable_Level"   # no step lowers the cost: a minimum to round-off
            break
        log.debug(f"sparse Gauss-Newton iteration {it}: cost {f:.10g}, lambda {lam:.2g}")
        small = small + 1 if (f_prev - f) < 1e-4 else 0   # chi2 moves by < 2e-4: statistically still
        f_prev = f
        if rel < 1e-13 or small >= 2:
            status = "Solved_To_Acceptable_Level"
            break
    viol = nlp.constraint_violation(x)
    ok = status in ("Solve_Succeeded", "Solved_To_Acceptable_Level") and viol <= 1e-6
    if viol > 1e-6:
        status = f"{status} but constraints violated by {viol:.3g}"
    sol = Solution(x, ok, status, it, f, 0.0, time.perf_counter() - t0, solver="sparse-lm",
                   info={"constraint_violation": viol})
    if not ok and nlp.settings.ipopt.raise_on_failure:
        raise SolverError(f"sparse Levenberg-Marquardt did not converge: {status} after {it} iterations. "
                          "Try a better initial guess or check that the data match the model.",
                          status=status, stats=sol.info)
    return sol
