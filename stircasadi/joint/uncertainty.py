"""Uncertainty at the optimum: Fisher information, Cramér-Rao bounds, identifiability, mismatch.

Equations
---------
Gaussian likelihood with whitened residuals r = (y - M(x)) / sigma:

    F = J_r^T J_r (+ P, the information of declared priors),   Cov(x) = Z (Z^T F Z)^+ Z^T

with Z a basis of the null space of the active equality constraints (the gauge that fixes a free
frame, Helmholtz reciprocity): the Cramér-Rao bound on the constraint manifold. Poisson:
F = s^2 J_M^T diag(1/mu) J_M. Every reported number q(x) (positions, unit normals, areas,
albedos, albedo x area, Phong parameters: ``report_function``) gets Cov(q) = J_q Cov(x) J_q^T.

Model mismatch is exposed, not hidden: with chi2 = ||r||^2 over dof = n_bins - n_free the
whitened residual's level, every std is multiplied by sqrt(chi2 / dof) when it exceeds its noise
level (1 + 5 sqrt(2 / dof)); the caller refuses the estimate above ``chi2_max``. A noise-free
twin (sigma at its floor) is rescaled the same way (the floor is not a noise level).

Identifiability: the data's information is weighed against the weak prior's,
P = diag(1 / range^2) (``PRIOR_RANGE``: albedo 1, area 1 m^2, position 1 m, tilt pi/2, ...), by the
generalised eigenproblem (Z^T F Z) u = lam (Z^T P Z) u, solved on Jacobi-scaled matrices as
F u = mu (F + P) u so strong and weak unknowns are judged alike. Directions with lam < 1 (the data
know them less than the prior) are unseen; along them the covariance is the prior's, elsewhere
the data's alone: a number that moves with an unseen direction gets an std of its plausible
range, one that barely touches it keeps its own.
A number whose std exceeds its threshold (``UncertaintySettings``) is not identifiable. Neglects: non-linearity beyond the linearisation at the
optimum; an unknown on an active bound gets the unconstrained interval (flagged).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
from scipy.linalg import eigh, null_space

from ..model.vertices import patch_quantities

__all__ = ["report_function", "QUANTITIES", "fisher", "equality_null_space", "PRIOR_RANGE", "prior_std_x", "degenerate"]

#: plausible range (theta units) of each kind of unknown: the weak prior along null directions
PRIOR_RANGE = {"albedo": 1.0, "area": 1.0, "specular": 1.0, "exponent": 100.0, "position": 1.0,
               "tilt": math.pi / 2, "tilt2": math.pi / 2, "fkij": 10.0 / math.pi, "ar1": 1.0}

#: reported per-patch quantities and their widths, in the order of ``report_function``
QUANTITIES = (("position", 3), ("normal", 3), ("area", 1), ("albedo", 1), ("albedo_area", 1),
              ("specular", 1), ("exponent", 1))


def equality_null_space(nlp, x) -> np.ndarray:
    """(n, n_free) orthonormal basis of the null space of the Jacobian of ``nlp``'s equality
    constraints at ``x`` (the gauge that fixes a free frame, Helmholtz reciprocity); the identity
    when there are none."""
    eq = np.flatnonzero(np.isfinite(nlp.lbg) & (nlp.lbg == nlp.ubg)) if len(nlp.lbg) else np.zeros(0, int)
    if not len(eq):
        return np.eye(len(nlp.lbx))
    A = np.asarray(ca.densify(ca.Function("Jg", [nlp.xx], [ca.jacobian(nlp.g, nlp.xx)])(x)))[eq]
    return null_space(A)


def _generalised_eigh(A, B):
    """Solve A u = mu B u for symmetric A and positive semi-definite B, robust to round-off.

    Cholesky-based ``eigh(A, B)`` first; when round-off leaves B (information plus a prior many
    decades weaker) a hair from positive definite, whiten by B's own eigendecomposition with its
    eigenvalues clipped at 1e-14 of the largest (the directions clipped carry no information)."""
    try:
        return eigh(A, B)
    except np.linalg.LinAlgError:
        s, V = np.linalg.eigh(B)
        s = np.maximum(s, 1e-14 * max(float(s.max(initial=0.0)), 1e-300))
        W = V / np.sqrt(s)[None, :]
        mu, Q = np.linalg.eigh(0.5 * (W.T @ A @ W + (W.T @ A @ W).T))
        return mu, W @ Q


def report_function(model):
    """CasADi function x -> q (all reported numbers, patch-major per quantity) and the layout
    {name: (offset, width)} of q."""
    pq = patch_quantities(model.theta_sym, model)
    M = model.M
    prod = ca.DM(model.albedo_product.astype(float)).T
    area = pq["area"]
    alb_param = pq["albedo"]
    albedo = prod * alb_param / area + (1 - prod) * alb_param
    alb_area = prod * alb_param + (1 - prod) * alb_param * area
    parts, layout, off = [], {}, 0
    for name, width in QUANTITIES:
        if name == "position":
            e = ca.vec(model.theta_sym["position"])            # (3M,) patch-major xyz
        elif name == "normal":
            e = ca.vec(ca.vertcat(*pq["n"]))
        else:
            e = {"area": area, "albedo": albedo, "albedo_area": alb_area,
                 "specular": pq["specular"], "exponent": pq["exponent"]}[name].T
        parts.append(e)
        layout[name] = (off, width)
        off += width * M
    q = ca.vertcat(*parts)
    return ca.Function("q", [model.x], [q, ca.jacobian(q, model.x)]), layout


def prior_std_x(nlp) -> np.ndarray:
    """The weak prior's std of each unknown of x (scaled units; ``PRIOR_RANGE``; albedo x area of
    a hidden patch: 0.05 m^2)."""
    m = nlp.model
    names = [b[0] for b in m.blocks] + (["ar1"] if nlp.pem else [])
    sc = np.concatenate([m.x_scale, [1.0] * (nlp.n_x - m.n_x)])
    out = []
    for (nm, k, _) in list(m.blocks) + ([("ar1", -1, 0)] if nlp.pem else []):
        if nm == "gain":
            out.append(5.0)
        elif nm == "albedo" and k >= 0 and m.albedo_product[k]:
            out.append(0.05)
        else:
            out.append(PRIOR_RANGE.get(nm, 1.0))
    del names
    return np.array(out) / sc


def fisher(nlp, x, prior_info=None, frozen=None) -> dict:
    """Information, covariance of x, chi2 and identifiability at ``x`` (see module docstring).

    Returns dict: ``cov_x`` (scaled x), ``chi2``, ``dof``, ``inflation`` (the std factor applied),
    ``null`` (x-space null vectors), ``sigma_used``, ``at_bound`` (bool per unknown),
    ``F`` (information on the constraint manifold, unscaled by inflation)."""
    us = nlp.settings.uncertainty
    x = np.asarray(x, float)
    n = nlp.n_x
    if nlp.poisson:
        JM = np.asarray(ca.densify(nlp.f_JM(x)))
        s = float(nlp.noise["scale"])
        mu = np.maximum(np.asarray(ca.Function("mu", [nlp.xx], [nlp.mu])(x)).ravel(), 1e-300)
        F = (s ** 2) * (JM.T * (1.0 / mu)) @ JM
        rr = (np.round(np.maximum(nlp.y * s, 0)) - mu) / np.sqrt(mu)
        chi2 = float(rr @ rr)
    else:
        F = nlp.information(x)
        r = nlp.residuals(x)
        chi2 = float(r @ r) + nlp.fold_const
    if prior_info is not None:
        F = F + prior_info
    frozen = np.asarray(frozen if frozen is not None else [], int)
    if len(frozen):  # unknowns held at their start: only the weak prior speaks for them
        F = F.copy()
        F[frozen, frozen] += 1.0 / prior_std_x(nlp)[frozen] ** 2
    Z = equality_null_space(nlp, x)  # equality constraints active at x: gauge, reciprocity
    n_free = Z.shape[1]
    dof = max(len(nlp.y) - n_free, 1)
    Fz = Z.T @ F @ Z
    Fz = 0.5 * (Fz + Fz.T)
    prior_std = prior_std_x(nlp)
    Pz = Z.T @ (Z / prior_std[:, None] ** 2)
    Pz = 0.5 * (Pz + Pz.T)
    # data against the weak prior, direction by direction: F v = lam P v, solved as
    # F v = mu (F + P) v (mu = lam / (1 + lam) in [0, 1]) on the Jacobi-scaled matrices, which
    # stays well conditioned however strong and weak unknowns differ (scale-free)
    dg = np.sqrt(np.maximum(np.diag(Fz) + np.diag(Pz), 1e-300))
    Fn = Fz / np.outer(dg, dg)
    Sn = Fn + Pz / np.outer(dg, dg)
    mu, U = _generalised_eigh(Fn, 0.5 * (Sn + Sn.T))  # U^T Sn U = I, U^T Fn U = diag(mu)
    mu = np.clip(mu, 0.0, 1.0)
    lam = mu / np.maximum(1.0 - mu, 1e-300)
    # a direction is unseen when the data know it less than the weak prior does, or when its
    # information is numerically nil and not clearly above the prior
    null_mask = (lam < 1.0) | ((lam < 10.0) & (lam < us.null_tol * max(lam.max(initial=0.0), 1e-300)))
    good = ~null_mask
    Ug, Un = U[:, good], U[:, null_mask]
    cov_z = (Ug / mu[good]) @ Ug.T  # data only where the data see
    cov_z = cov_z + (Un / np.maximum(1.0 - mu[null_mask], 1e-300)) @ Un.T  # the prior fills the rest
    cov_z = cov_z / np.outer(dg, dg)
    cov_x = Z @ cov_z @ Z.T
    null = Z @ (Un / dg[:, None]) if null_mask.any() else np.zeros((n, 0))
    sigma_used = nlp.sigma
    red = chi2 / dof
    inflation = 1.0
    if nlp.sigma_source.startswith("floor"):
        inflation = math.sqrt(max(red, 1e-300))
        sigma_used = nlp.sigma * inflation
    elif us.chi2_inflate and red > 1.0 + 5.0 * math.sqrt(2.0 / dof):
        inflation = math.sqrt(red)
    cov_x = cov_x * inflation ** 2
    rng = nlp.ubx - nlp.lbx
    at_bound = np.zeros(n, bool)
    fin = np.isfinite(rng) & (rng > 0)
    at_bound[fin] = (np.minimum(x[fin] - nlp.lbx[fin], nlp.ubx[fin] - x[fin]) < 1e-6 * rng[fin])
    return {"cov_x": cov_x, "chi2": chi2, "dof": dof, "chi2_dof": red, "inflation": inflation,
            "null": null, "null_dim": int(null_mask.sum()), "sigma_used": float(sigma_used),
            "at_bound": at_bound, "F": F}


#: which unknowns are held first when the information is singular (most often unidentified)
_FREEZE_ORDER = ("tilt2", "tilt", "area", "specular", "exponent", "albedo", "gain", "position")


def degenerate(nlp, x, tol: float = 1e-8, max_freeze: int | None = None) -> list[int]:
    """Unknowns to hold at their start so the information at ``x`` is not nearly singular: while
    the weakest direction of the correlation-normalised information (on the equality
    constraints' manifold) has an eigenvalue below ``tol`` and the data know it less than 25
    times better than the weak prior (its std above a fifth of its plausible range), the unknown
    of that direction with the largest weight, of the kind first in ``_FREEZE_ORDER``, is held.
    A well-posed problem returns []."""
    x = np.asarray(x, float)
    if nlp.poisson:
        return []
    F = nlp.information(x)
    if getattr(nlp, "r_prior", None) is not None:
        Jp = nlp.prior_jacobian(x)
        F = F + np.asarray((Jp.T @ Jp).todense())
    n = nlp.n_x
    eq = np.flatnonzero(np.isfinite(nlp.lbg) & (nlp.lbg == nlp.ubg)) if len(nlp.lbg) else np.zeros(0, int)
    if len(eq):
        A = np.asarray(ca.densify(ca.Function("Jg", [nlp.xx], [ca.jacobian(nlp.g, nlp.xx)])(x)))[eq]
    else:
        A = np.zeros((0, n))
    names = [b[0] for b in nlp.model.blocks] + (["ar1"] if nlp.pem else [])
    rank = {k: i for i, k in enumerate(_FREEZE_ORDER)}
    frozen: list[int] = []
    for _ in range(max_freeze if max_freeze is not None else n):
        keep = np.setdiff1d(np.arange(n), frozen)
        Ak = A[:, keep]
        Z = null_space(Ak) if len(Ak) else np.eye(len(keep))
        Fz = Z.T @ F[np.ix_(keep, keep)] @ Z
        dg = np.sqrt(np.maximum(np.diag(Fz), 1e-300))
        ev, V = np.linalg.eigh(Fz / np.outer(dg, dg))
        Vx = Z @ (V[:, :1] / dg[:, None])
        pinfo = float(np.sum(Vx[:, 0] ** 2 / prior_std_x(nlp)[keep] ** 2))
        if ev[0] >= tol * max(ev[-1], 1e-300) or ev[0] >= 25.0 * pinfo:
            break            # the weakest direction is seen by the data (std < a fifth of its range)
        v = np.abs(Vx[:, 0])                       # the weakest direction, in the unknowns
        v = v / v.max()
        cand = np.flatnonzero(v > 0.05)
        j = min(cand, key=lambda c: (rank.get(names[keep[c]], 99), -v[c]))
        frozen.append(int(keep[j]))
    return frozen
