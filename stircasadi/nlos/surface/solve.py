"""One IPOPT solve of a level's surface NLP (CasADi ``nlpsol`` over a Callback objective).

The NLP, in scaled unknowns x = [(z - z_c) / s_z, rho / s_rho, log(sigma / sigma_c), b / s_b]:

    min  F(x) = 1/2 sum_pk wgt_pk (m_pk(x) - y_pk)^2 + 1/2 lam || Lap z / h ||^2
    s.t. |z - z_c| <= slack,  0 <= rho <= rho_max,  sigma in [sigma_c / 2, 2 sigma_c]

(rho_max = 1 with an absolute relay gain: a hard physical rule, not a penalty). The objective
and its exact gradient come from ``SurfaceModel.value_and_grad`` (CasADi AD of the pair model);
IPOPT runs with its limited-memory Hessian, since the Gauss-Newton matrix of a surface couples
every node with every other (dense) and is formed only once, for the Fisher information.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

__all__ = ["solve_level"]


class _Objective(ca.Callback):
    """F(x) with its gradient as the Callback's Jacobian (evaluated once per new x)."""

    def __init__(self, fn, n):
        ca.Callback.__init__(self)
        self.fn, self.n = fn, n
        self._x, self._f, self._g = None, None, None
        self.construct("surface_objective", {"enable_fd": False})

    def _eval(self, x):
        x = np.asarray(x, float).ravel()
        if self._x is None or not np.array_equal(x, self._x):
            self._f, self._g = self.fn(x)
            self._x = x.copy()
        return self._f, self._g

    def get_n_in(self):
        return 1

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.n, 1)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(1, 1)

    def eval(self, arg):
        return [self._eval(arg[0])[0]]

    def has_jacobian(self):
        return True

    def get_jacobian(self, name, inames, onames, opts):
        self._grad = _Gradient(self, name)
        return self._grad


class _Gradient(ca.Callback):
    def __init__(self, obj, name):
        ca.Callback.__init__(self)
        self.obj = obj
        self.construct(name, {"enable_fd": False})

    def get_n_in(self):
        return 2

    def get_n_out(self):
        return 1

    def get_sparsity_in(self, i):
        return ca.Sparsity.dense(self.obj.n, 1) if i == 0 else ca.Sparsity.dense(1, 1)

    def get_sparsity_out(self, i):
        return ca.Sparsity.dense(1, self.obj.n)

    def eval(self, arg):
        return [ca.DM(self.obj._eval(arg[0])[1][None, :])]


def solve_level(model, y, wgt, z_c, rho0, sigma_c, bg0, lam, lap, h, slack, rho_max,
                fit_sigma, max_iter, tol, s_rho, s_b):
    """Run IPOPT on one level. Returns dict(z, rho, sigma, bg, status, iterations, f)."""
    N = model.N
    s_z = max(slack / 3.0, 1e-4)
    n = 2 * N + (1 if fit_sigma else 0) + 1
    Lz = lap

    def unpack(x):
        z = z_c + s_z * x[:N]
        rho = s_rho * x[N:2 * N]
        sig = sigma_c * np.exp(x[2 * N]) if fit_sigma else sigma_c
        bg = s_b * x[-1]
        return z, rho, sig, bg

    def fn(x):
        z, rho, sig, bg = unpack(x)
        m, e, (gz, grho, gsig, gbg) = model.value_and_grad(z, rho, sig, bg, y=y, wgt=wgt)
        r = m - y
        f = 0.5 * float(np.sum(wgt * r * r))
        if lam > 0:
            q = Lz @ z / h
            f += 0.5 * lam * float(q @ q)
            gz = gz + lam * (Lz.T @ q) / h
        g = np.concatenate([gz * s_z, grho * s_rho] + ([np.array([gsig * sig])] if fit_sigma else [])
                           + [np.array([gbg * s_b])])
        return f, g

    cb = _Objective(fn, n)
    x = ca.MX.sym("x", n)
    opts = {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes",
            "ipopt.hessian_approximation": "limited-memory", "ipopt.max_iter": int(max_iter),
            "ipopt.tol": float(tol), "ipopt.limited_memory_max_history": 30,
            "ipopt.acceptable_iter": 10, "ipopt.acceptable_tol": 1e-5}
    solver = ca.nlpsol("surface", "ipopt", {"x": x, "f": cb(x)}, opts)
    lb = np.concatenate([-3.0 * np.ones(N), np.zeros(N)] + ([np.array([np.log(0.5)])] if fit_sigma else [])
                        + [np.array([-np.inf])])
    ub = np.concatenate([3.0 * np.ones(N), np.full(N, rho_max / s_rho)]
                        + ([np.array([np.log(2.0)])] if fit_sigma else []) + [np.array([np.inf])])
    x0 = np.concatenate([np.zeros(N), np.clip(rho0 / s_rho, 0, ub[N:2 * N])]
                        + ([np.array([0.0])] if fit_sigma else []) + [np.array([bg0 / s_b])])
    res = solver(x0=x0, lbx=lb, ubx=ub)
    st = solver.stats()
    xs = np.asarray(res["x"], float).ravel()
    z, rho, sig, bg = unpack(xs)
    at_bound = bool(np.any(np.abs(xs[:N]) > 2.95))
    return {"z": z, "rho": rho, "sigma": float(sig), "bg": float(bg),
            "status": str(st.get("return_status")), "iterations": int(st.get("iter_count", 0)),
            "success": bool(st.get("success", False)) or st.get("return_status") in
            ("Solve_Succeeded", "Solved_To_Acceptable_Level"),
            "f": float(res["f"]), "z_at_slack": at_bound,
            "sigma_at_bound": bool(fit_sigma and abs(abs(xs[2 * N]) - np.log(2.0)) < 1e-3)}
