"""Uncertainty at the optimum: Fisher information (Gauss-Newton), Cramer-Rao bounds, identifiability.

Equations
---------
Gaussian likelihood with residuals r = W (y - M(x)) and Cov(y) = sigma^2 I:

    H = J_r^T J_r,     Cov(x) = H^+ J_r^T Cov(r) J_r H^+,     Cov(r) = sigma^2 W^2

which is H^+ (the Cramer-Rao bound) when W = 1/sigma (maximum likelihood); with W chosen for
another purpose (``weighting="relative"``) it is the sandwich estimate. When sigma is unknown
(noise-free twin, floor sigma) it is rescaled by s^2 = ||r||^2 / (N - p). Poisson:
F = s^2 J_M^T diag(1/mu) J_M. The unknowns' covariance is mapped back through the scales
(theta = offset + scale x). PEM: the AR(1) coefficient is part of x and of H.

Identifiability: H is eigen-decomposed in the scaled variables; directions with eigenvalue below
``null_tol`` x the largest are the null space, and every unknown with weight in it gets an
infinite standard deviation. An unknown whose standard deviation exceeds its threshold
(``UncertaintySettings``) is flagged unidentifiable: its value is not reported as a result.

What it neglects: the intervals are local (linearised at the optimum); an unknown on an active
bound gets the unconstrained interval (flagged ``at_bound``).
"""
from __future__ import annotations

import numpy as np


def fisher_uncertainty(nlp, x) -> dict:
    """Covariance, standard deviations, correlations and identifiability flags at ``x``.

    Returns a dict with ``cov_x`` (scaled), ``std_x``, ``std_theta`` (per unknown, in the
    parameter's units), ``corr``, ``eigvals``, ``null_dim``, ``identifiable`` (bool per unknown),
    ``at_bound`` and ``sigma_used``.
    """
    us = nlp.settings.uncertainty
    x = np.asarray(x, float)
    n = nlp.n_x
    scale = np.concatenate([nlp.model.x_scale, [1.0] * (n - nlp.model.n_x)])
    sigma_used = nlp.sigma
    if nlp.poisson:
        JM = np.asarray(nlp.f_JM(x).full())
        s = float(nlp.noise["scale"])
        mu = np.maximum(np.asarray(_eval(nlp.mu, nlp.xx, x)).ravel(), 1e-300)
        H = (s ** 2) * (JM.T * (1.0 / mu)) @ JM
        meat = None
    else:
        J = nlp.jacobian(x)
        r = nlp.residuals(x)
        H = J.T @ J
        meat = None
        if nlp.settings.cost.weighting != "noise":
            # sandwich: Cov(r) = sigma^2 W^2 (unfolded residuals; PEM whitening ignored here)
            Jy = np.asarray(nlp.f_JM(x).full()) * nlp.w[:, None] ** 2 * nlp.sigma
            meat = Jy.T @ Jy
        if nlp.sigma_source.startswith("floor"):
            dof = max(len(nlp.y) - n, 1)
            s2 = (float(r @ r) + nlp.fold_const) / dof
            H = H / max(s2, 1e-300)
            sigma_used = nlp.sigma * np.sqrt(s2)
    Hs = 0.5 * (H + H.T)
    # eigen-analysis of the correlation-normalised information (scale-free): D^-1/2 H D^-1/2
    dg = np.sqrt(np.clip(np.diag(Hs), 0.0, None))
    no_info = dg <= 1e-300
    dsafe = np.where(no_info, 1.0, dg)
    Hn = Hs / np.outer(dsafe, dsafe)
    Hn[no_info, :] = 0.0
    Hn[:, no_info] = 0.0
    ev, V = np.linalg.eigh(Hn)
    null = ev <= us.null_tol
    inv_ev = np.where(null, 0.0, 1.0 / np.where(null, 1.0, ev))
    Hp = ((V * inv_ev) @ V.T) / np.outer(dsafe, dsafe)
    cov = Hp if meat is None else Hp @ meat @ Hp
    var = np.clip(np.diag(cov), 0.0, None)
    in_null = (np.abs(V[:, null]) ** 2).sum(axis=1) > 1e-6 if null.any() else np.zeros(n, bool)
    std_x = np.sqrt(var)
    std_x[in_null] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sqrt(var)
        corr = cov / np.outer(d, d)
    corr[~np.isfinite(corr)] = np.nan
    std_theta = std_x * scale
    ident = np.ones(n, bool)
    m = nlp.model
    eps_pos = us.max_position_std if us.max_position_std is not None else nlp.settings.constraints.hidden_eps
    theta_vals = m.x_offset + m.x_scale * x[:m.n_x]
    for j in range(n):
        if not np.isfinite(std_theta[j]):
            ident[j] = False
            continue
        if j >= m.n_x:
            continue
        name = m.blocks[j][0]
        if name in ("albedo", "specular"):
            ident[j] = std_theta[j] <= us.max_rel_std * (m.ubx[j] - m.lbx[j]) * m.x_scale[j]
        elif name in ("exponent", "fkij"):
            ident[j] = std_theta[j] <= us.max_rel_std * max(abs(theta_vals[j]), m.x_scale[j])
        elif name in ("position", "distance"):
            ident[j] = std_theta[j] <= eps_pos
        elif name in ("tilt", "tilt2"):
            ident[j] = std_theta[j] <= np.radians(us.max_tilt_std_deg)
    tol = 1e-6
    at_bound = (x <= nlp.lbx + tol) | (x >= nlp.ubx - tol)
    pos_std = _distance_position_std(m, x, cov)
    nrm_std = _normal_std(m, x, cov)
    return {"position_std_from_distances": pos_std, "normal_std": nrm_std, "cov_x": cov, "std_x": std_x, "std_theta": std_theta, "corr": corr, "eigvals": ev,
            "null_dim": int(null.sum()), "identifiable": ident, "at_bound": at_bound,
            "sigma_used": float(sigma_used)}


def _eval(expr, xx, x):
    import casadi as ca

    return ca.Function("tmp", [xx], [expr])(x).full()


def _distance_position_std(m, x, cov) -> dict:
    """Position std (3,) of distance-parameterised patches: J_p Cov(d) J_p^T (CasADi Jacobian)."""
    import casadi as ca

    out = {}
    th = m.theta(x[:m.n_x])
    for k in np.flatnonzero(m.param("distance").free):
        js = [j for j, (n, kk, c) in enumerate(m.blocks) if n == "distance" and kk == k]
        if len(js) != 2:
            continue
        d = ca.MX.sym("d", 2)
        Jp = ca.Function("Jp", [d], [ca.jacobian(m._trilaterate(k, d[0], d[1]), d)])(th["distance"][k]).full()
        S = np.diag(m.x_scale[js])
        C = S @ cov[np.ix_(js, js)] @ S
        out[int(k)] = np.sqrt(np.clip(np.diag(Jp @ C @ Jp.T), 0, None))
    return out


def _normal_std(m, x, cov) -> dict:
    """Normal std (3,) of patches with free tilts: J_n Cov(tilt, tilt2) J_n^T (analytic J_n)."""
    out = {}
    th = m.theta(x[:m.n_x])
    n0, ax = m.normals, m.tilt_axis
    u = np.cross(ax, n0)
    for k in np.flatnonzero(m.tilt_free):
        a, b = th["tilt"][k], th["tilt2"][k]
        dn_da = np.cos(b) * (-np.sin(a) * n0[k] + np.cos(a) * u[k])
        dn_db = -np.sin(b) * (np.cos(a) * n0[k] + np.sin(a) * u[k]) + np.cos(b) * ax[k]
        cols, js = [], []
        for name, dn in (("tilt", dn_da), ("tilt2", dn_db)):
            j = [i for i, (n, kk, c) in enumerate(m.blocks) if n == name and kk == k]
            if j:
                cols.append(dn)
                js.append(j[0])
        J = np.array(cols).T                       # (3, p)
        S = np.diag(m.x_scale[js])
        C = S @ cov[np.ix_(js, js)] @ S
        out[int(k)] = np.sqrt(np.clip(np.diag(J @ C @ J.T), 0, None))
    return out
