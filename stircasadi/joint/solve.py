"""The one IPOPT driver of the project, and the joint NLP's solve with curvature scaling.

``ipopt(...)`` builds a CasADi ``nlpsol`` (IPOPT), runs it, checks the return status and returns a
``Solution``; the joint NLP (``solve_nlp``) and the geometry stage's bounded embedding
(``geometry/embedding.py``) both call it, so options, status checks and timing live here once.

A failed solve is never returned as a result: ``Solution.success`` is False and, with
``raise_on_failure``, a ``SolverError`` names the status and what to try.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..errors import SolverError

__all__ = ["Solution", "ipopt", "solve_nlp", "OK_STATUS"]

OK_STATUS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


@dataclass
class Solution:
    """What one solve returns (x in the caller's variables)."""

    x: np.ndarray
    success: bool
    status: str
    iterations: int
    cost: float
    build_time_s: float
    solve_time_s: float
    lam_x: np.ndarray | None = None
    lam_g: np.ndarray | None = None
    solver: str = "ipopt"
    info: dict = field(default_factory=dict)


def ipopt(x, f, g, x0, lbx, ubx, lbg=(), ubg=(), options: dict | None = None, name: str = "nlp",
          hess_lag=None, lam_x0=None, lam_g0=None, raise_on_failure: bool = False,
          what: str = "IPOPT") -> Solution:
    """Solve min f(x) s.t. lbg <= g(x) <= ubg, lbx <= x <= ubx with IPOPT (CasADi symbols)."""
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}
    for k, v in (options or {}).items():
        opts[k if (k.startswith("ipopt.") or k in ("print_time", "hess_lag", "expand")) else f"ipopt.{k}"] = v
    if hess_lag is not None:
        opts["hess_lag"] = hess_lag
    t0 = time.perf_counter()
    solver = ca.nlpsol(name, "ipopt", {"x": x, "f": f, "g": g}, opts)
    t_build = time.perf_counter() - t0
    args = dict(x0=np.asarray(x0, float), lbx=np.asarray(lbx, float), ubx=np.asarray(ubx, float))
    if len(lbg):
        args.update(lbg=np.asarray(lbg, float), ubg=np.asarray(ubg, float))
    if lam_x0 is not None:
        args["lam_x0"] = lam_x0
    if lam_g0 is not None:
        args["lam_g0"] = lam_g0
    t1 = time.perf_counter()
    sol = solver(**args)
    t_solve = time.perf_counter() - t1
    st = solver.stats()
    status = st.get("return_status", "unknown")
    ok = bool(st.get("success", False)) and status in OK_STATUS
    out = Solution(np.asarray(sol["x"]).ravel(), ok, status, int(st.get("iter_count", -1)),
                   float(sol["f"]), t_build, t_solve, np.asarray(sol["lam_x"]).ravel(),
                   np.asarray(sol["lam_g"]).ravel())
    if not ok and raise_on_failure:
        raise SolverError(f"{what} did not converge: return_status '{status}' after {out.iterations} "
                          f"iterations (cost {out.cost:.6g}). Allowed: {OK_STATUS}. Try a better "
                          "initial guess, hessian='exact', more max_iter, or check that the data "
                          "match the model (bounces, IRF).", status=status,
                          stats={"iterations": out.iterations, "cost": out.cost})
    return out


def solve_nlp(nlp, x0=None, warm: Solution | None = None) -> Solution:
    """Solve a ``JointNLP`` with IPOPT (exact, Gauss-Newton or L-BFGS Hessian).

    Curvature scaling: IPOPT works on xi = d x with d_j = max(sqrt(F_jj(x0)), 1) (F the
    Gauss-Newton information), so a first-bounce albedo (F ~ 1e18) and a 1e-6 third-bounce one
    (F ~ 1e6) look alike to its tolerances: ``tol`` is then a fraction of one standard deviation.
    """
    st = nlp.settings.ipopt
    x_init = np.asarray(warm.x if warm is not None else (nlp.x0 if x0 is None else x0), float)
    x_init = np.clip(x_init, nlp.lbx, nlp.ubx)
    d = nlp.curvature_scale(x_init) if st.curvature_scaling else np.ones(nlp.n_x)
    opts = {"tol": st.tol, "max_iter": st.max_iter, "honor_original_bounds": "yes",
            "acceptable_tol": st.acceptable_tol, "acceptable_iter": 5, "print_level": st.print_level,
            "nlp_scaling_method": "none" if st.curvature_scaling else "gradient-based"}
    xi = ca.MX.sym("xi", nlp.n_x)
    fg = ca.Function("fg", [nlp.xx], [nlp.f, nlp.g])
    f_xi, g_xi = fg(xi / ca.DM(d))
    hess = None
    if st.hessian == "limited-memory":
        opts["hessian_approximation"] = "limited-memory"
    elif st.hessian == "gauss-newton":
        hx = nlp.hessian_function()
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", nlp.g.shape[0])
        p = ca.MX.sym("p", 0)
        Dinv = ca.diag(ca.DM(1.0 / d))
        Hxi = ca.mtimes(Dinv, ca.mtimes(ca.triu2symm(hx(xi / ca.DM(d), p, lam_f, lam_g)), Dinv))
        hess = ca.Function("hess_xi", [xi, p, lam_f, lam_g], [ca.triu(Hxi)])
    lam_x0 = lam_g0 = None
    if warm is not None:
        opts.update({"warm_start_init_point": "yes", "mu_init": 1e-6, "warm_start_bound_push": 1e-9,
                     "warm_start_mult_bound_push": 1e-9})
        if warm.lam_x is not None and len(warm.lam_x) == nlp.n_x:
            lam_x0 = warm.lam_x / d
        if warm.lam_g is not None and len(warm.lam_g) == len(nlp.lbg):
            lam_g0 = warm.lam_g
    opts.update(st.extra)
    if getattr(nlp, "budget", None) is not None:
        opts.update(nlp.budget.ipopt_options())
    sol = ipopt(xi, f_xi, g_xi, x_init * d, nlp.lbx * d, nlp.ubx * d, nlp.lbg, nlp.ubg, opts,
                name="joint", hess_lag=hess, lam_x0=lam_x0, lam_g0=lam_g0)
    sol.x = sol.x / d
    sol.lam_x = sol.lam_x * d
    sol.info.update({"hessian": st.hessian, "curvature_scale_range": [float(d.min()), float(d.max())],
                     "constraint_violation": nlp.constraint_violation(sol.x)})
    if not sol.success and st.raise_on_failure:
        raise SolverError(f"IPOPT did not converge: return_status '{sol.status}' after "
                          f"{sol.iterations} iterations (cost {sol.cost:.6g}). Allowed: {OK_STATUS}. "
                          "Try a better initial guess, hessian='exact', more max_iter, or check that "
                          "the data match the model (bounces, IRF).", status=sol.status,
                          stats={"iterations": sol.iterations, "cost": sol.cost})
    return sol
