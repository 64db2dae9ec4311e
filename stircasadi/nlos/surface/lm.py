"""Bounded Levenberg-Marquardt on a level's surface NLP (the default solver of ``fit_surface``).

Same NLP as ``solve.py`` (whitened least squares + smoothness prior; 0 <= rho <= rho_max and
sigma within [sigma_lo, sigma_hi] as hard bounds), solved with the exact Gauss-Newton matrix
H = J^T W J built from the CasADi pair Jacobians: each iteration solves
(H + lam R + mu diag(H)) d = -g, limits the depth step to ``slack``, projects onto the bounds,
re-centres the deposit windows, and accepts the step when the objective decreases (mu / 3) or
retries with mu x 4. It needs 5-20 iterations where IPOPT's limited-memory Hessian needed
hundreds on the same problems (the GN matrix is dense: every node couples with every other, so
IPOPT cannot take it as its exact Hessian at useful sizes).
"""
from __future__ import annotations

import numpy as np

__all__ = ["solve_lm"]


def solve_lm(model, y, wgt, z, rho, sigma, bg, lam, lap, h, slack, rho_max, fit_sigma,
             sigma_bounds, max_iter=30, tol=1e-6):
    """Returns dict(z, rho, sigma, bg, status, iterations, success, f, H, g)."""
    N = model.N
    Rz = (lap.T @ lap).toarray() / h ** 2

    def objective(z, rho, sigma, bg):
        m = model.predict(z, rho, sigma, bg)
        r = m - y
        f = 0.5 * float(np.sum(wgt * r * r))
        if lam > 0:
            q = lap @ z / h
            f += 0.5 * lam * float(q @ q)
        return f

    def pack_grad(z, rho, sigma, bg):
        m, e, (gz, grho, gsig, gbg) = model.value_and_grad(z, rho, sigma, bg, y=y, wgt=wgt)
        if lam > 0:
            gz = gz + lam * (Rz @ z)
        g = np.concatenate([gz, grho] + ([np.array([gsig])] if fit_sigma else []) + [np.array([gbg])])
        return g

    model.recentre(z)
    f = objective(z, rho, sigma, bg)
    mu = 1e-3
    status, it = "Maximum_Iterations_Exceeded", 0
    H = g = None
    for it in range(1, max_iter + 1):
        H = model.gauss_newton(z, rho, sigma, wgt, fit_sigma)
        g = pack_grad(z, rho, sigma, bg)
        Hp = H.copy()
        if lam > 0:
            Hp[:N, :N] += lam * Rz
        dH = np.maximum(np.diag(Hp), 1e-12 * max(float(np.max(np.diag(Hp))), 1e-300))
        accepted = False
        for _ in range(12):
            A = Hp + mu * np.diag(dH)
            try:
                d = -np.linalg.solve(A, g)
            except np.linalg.LinAlgError:
                mu *= 10
                continue
            dz = d[:N]
            big = float(np.max(np.abs(dz))) if N else 0.0
            if big > slack:
                d = d * (slack / big)
            zn = z + d[:N]
            rn = np.clip(rho + d[N:2 * N], 0.0, rho_max)
            sn = float(np.clip(sigma + d[2 * N], *sigma_bounds)) if fit_sigma else sigma
            bn = bg + d[-1]
            model.recentre(zn)
            fn = objective(zn, rn, sn, bn)
            if fn < f:
                accepted = True
                rel = (f - fn) / max(abs(f), 1e-300)
                z, rho, sigma, bg, f = zn, rn, sn, bn, fn
                mu = max(mu / 3.0, 1e-9)
                break
            model.recentre(z)
            mu *= 4.0
        if not accepted:
            status = "Converged (no decrease possible)"
            break
        if rel < tol:
            status = "Converged"
            break
    model.recentre(z)
    return {"z": z, "rho": rho, "sigma": float(sigma), "bg": float(bg), "status": status,
            "iterations": it, "success": status.startswith("Converged"), "f": f}
