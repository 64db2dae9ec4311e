"""One IPOPT solve of a level's surface NLP (CasADi ``nlpsol`` over a Callback objective).

The NLP is the one ``lm.py`` states (whitened least squares + smoothness prior, albedo and
response bounds; rho_max = 1 with an absolute relay gain: a hard physical rule, not a penalty),
in unknowns scaled to about 1. The objective and its exact gradient come from
``SurfaceModel.linearise`` (CasADi AD of the pair geometry, the response's derivatives);
IPOPT runs with its limited-memory Hessian, since the Gauss-Newton matrix of a surface couples
every node with every other (dense) and is formed only once, for the Fisher information.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from .lm import prior_vector

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


def solve_level(model, y, wgt, st, lam, R_prior, bounds, max_iter, tol) -> dict:
    """Run IPOPT on one level from ``st``. Returns dict(state, status, iterations, success, f)."""
    N = model.N
    th0 = bounds.project(model.pack(st))
    scale = np.maximum(np.abs(th0), 1e-3)
    scale[:N] = max(float(np.std(th0[:N])), 1e-3)
    scale[N:2 * N] = max(float(np.max(th0[N:2 * N])), 1e-3)
    shift = np.zeros_like(th0)
    shift[:N] = th0[:N]

    def fn(x):
        th = shift + scale * x
        s = model.unpack(th, st)
        lin = model.linearise(s, y, wgt, need_h=False)
        f, g = 0.5 * lin["chi2"], lin["g"]
        if lam > 0:
            v = prior_vector(s, R_prior.shape[0])
            q = R_prior @ v
            f += 0.5 * lam * float(v @ q)
            g = g.copy()
            g[:len(v)] += lam * q
        return f, g * scale

    cb = _Objective(fn, model.npar)
    x = ca.MX.sym("x", model.npar)
    opts = {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes",
            "ipopt.hessian_approximation": "limited-memory", "ipopt.max_iter": int(max_iter),
            "ipopt.tol": float(tol), "ipopt.limited_memory_max_history": 30,
            "ipopt.acceptable_iter": 10, "ipopt.acceptable_tol": 1e-5}
    solver = ca.nlpsol("surface", "ipopt", {"x": x, "f": cb(x)}, opts)
    res = solver(x0=(th0 - shift) / scale, lbx=(bounds.lo - shift) / scale, ubx=(bounds.hi - shift) / scale)
    stats = solver.stats()
    th = bounds.project(shift + scale * np.asarray(res["x"], float).ravel())
    return {"state": model.unpack(th, st), "status": str(stats.get("return_status")),
            "iterations": int(stats.get("iter_count", 0)),
            "success": bool(stats.get("success", False)) or stats.get("return_status") in
            ("Solve_Succeeded", "Solved_To_Acceptable_Level"),
            "f": float(res["f"]), "at_bound": [n for i, n in enumerate(model.glob)
                                               if bounds.at_bound(th)[2 * N + i]]}
