"""The smoothness prior's weight of one level (step 4 of ``fit.py``): the discrepancy principle
or generalised cross-validation on the level's linearisation.

When to use: called by ``fit_surface`` with ``prior="auto"`` or ``"gcv"``; nothing else needs it.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve

__all__ = ["GCV_PROBES", "prior_operator", "step_chi2", "rejected"]


#: Rademacher probes of the GCV trace estimate (seeded: the same probes for every candidate)
GCV_PROBES = 64


def _choose_lambda(H, g, chi2, dof, R, N, lam_now, z=None, slack=np.inf, out_info=None, rule="discrepancy"):
    """Discrepancy principle on the linearised problem at the current solution ``z``: for each
    candidate weight lam, the linearised minimiser of chi^2 + lam z^T R z (step d from
    (H + lam R) d = -(g + lam R z)) and its predicted data chi^2; the largest lam whose chi^2
    stays within max(c_ref, dof) (1 + 2 sqrt(2 / dof)). c_ref, the best chi^2 the model reaches,
    is the lowest prediction among the steps the linearisation holds for (depth changes within
    ``slack``) and the chi^2 reached: on a fine grid whose solve has not converged the
    unregularised Gauss-Newton step is metres long and its predicted chi^2 far below anything a
    step reaches, which would leave no weight passing.

    ``out_info`` (a dict) receives ``c_ref`` and ``target``, ``slack_bound`` (c_ref is above the
    lowest prediction of all candidates: the weights whose steps leave the slack were set aside)
    and ``lam_unbounded``, the weight the same rule gives with every candidate's step trusted. A
    slack-bound choice is set by how far the state is from the fit's minimum, not by the noise:
    on the real resolution chart after 12 iterations per level the 8 x 8 weight 4 084 keeps the
    linearised chi2/dof at 5.93 against 5.12 at weight 0 (the rule's tolerance is 1.3 %), and its
    16 x 16 weight 38 at 3.50 against 3.34.

    ``rule="gcv"``: generalised cross-validation instead, the candidate minimising
    V = n c / (n - edf)^2 (n = dof + unknowns data, c the linearised chi^2 of its step,
    edf = tr(H (H + lam R)^-1) the fit's effective number of unknowns, estimated from
    ``GCV_PROBES`` seeded Rademacher probes through the same Cholesky factor) among the candidates
    whose steps the linearisation holds for (all when none does: ``out_info["slack_bound"]``).
    V does not use the noise level: a model mismatch that scales chi^2 (chi2/dof ~ 4 on the real
    charts) scales V alike and leaves its minimum where it was. ``out_info`` then also receives
    ``V`` and ``edf`` at the choice."""
    npar = H.shape[0]
    M = R.shape[0]          # the prior's unknowns: the depths (N), or the depths and albedos (2 N)
    Rf = np.zeros_like(H)
    Rf[:M, :M] = R
    th = np.zeros(npar)
    if z is not None:
        th[:M] = z
    hz = float(np.trace(H[:N, :N])) / max(np.trace(R[:N, :N]), 1e-300)
    cands = np.concatenate([[0.0], hz * np.logspace(-8, 2, 41)])
    ridge = 1e-10 * float(np.trace(H)) / npar + 1e-300
    out, valid, steps = [], [chi2], {}
    gcv = rule == "gcv"
    if gcv:
        probes = np.random.default_rng(0).choice([-1.0, 1.0], size=(npar, GCV_PROBES))
        Hp = H @ probes
        n_data = dof + npar
        scored = []          # (lam, c, edf, trusted)
    Rth = Rf @ th
    for lam in cands:
        A = H + lam * Rf
        A[np.diag_indices(npar)] += ridge
        try:   # A is symmetric positive definite (H and R semi-definite, the ridge): Cholesky
            fac = cho_factor(A, check_finite=False)
            dlt = -cho_solve(fac, g + lam * Rth, check_finite=False)
            edf = float(np.sum(probes * cho_solve(fac, Hp, check_finite=False))) / GCV_PROBES if gcv else None
        except (np.linalg.LinAlgError, ValueError):
            try:
                dlt = -np.linalg.solve(A, g + lam * Rth)
                edf = float(np.sum(probes * np.linalg.solve(A, Hp))) / GCV_PROBES if gcv else None
            except np.linalg.LinAlgError:
                continue
        c = chi2 + 2 * g @ dlt + dlt @ H @ dlt
        out.append((lam, c))
        steps[lam] = dlt
        trusted = float(np.max(np.abs(dlt[:N]))) <= slack
        if trusted:
            valid.append(c)
        if gcv:
            scored.append((lam, c, edf, trusted))
    if not out:
        return lam_now, []
    if gcv:
        V = np.array([n_data * max(c, 0.0) / max(n_data - e, 1.0) ** 2 for _, c, e, _ in scored])
        ok = np.array([r[3] for r in scored])
        k_all = int(np.argmin(V))
        k = int(np.flatnonzero(ok)[np.argmin(V[ok])]) if ok.any() else k_all
        if out_info is not None:
            # slack-bound: the minimum over every candidate is at a step longer than trusted
            out_info.update({"rule": "gcv", "V": float(V[k]), "edf": float(scored[k][2]),
                             "c_ref": float(scored[k][1]), "target": None, "slack_bound": k != k_all,
                             "lam_unbounded": float(scored[k_all][0])})
        return float(scored[k][0]), out
    tol = 1 + 2 * math.sqrt(2.0 / max(dof, 1))
    target = max(min(valid), dof) * tol
    ok = [lam for lam, c in out if c <= target]
    if out_info is not None:
        lowest = min(c for _, c in out)
        t_all = max(min(lowest, chi2), dof) * tol
        ok_all = [lam for lam, c in out if c <= t_all]
        out_info.update({"c_ref": float(min(valid)), "target": float(target),
                         "slack_bound": bool(min(valid) > min(lowest, chi2) * (1 + 1e-12)),
                         "lam_unbounded": float(max(ok_all)) if ok_all else 0.0})
    lam = max(ok) if ok else 0.0
    if out_info is not None:
        out_info["step"] = steps.get(lam)      # the chosen weight's linearised step (or None)
    return lam, out


def step_chi2(model, state, bounds, step, y, wgt) -> float:
    """The data's whitened chi^2 at ``state`` moved by a weight's linearised step (projected
    onto ``bounds``): what the linearisation predicted, on the nonlinear model."""
    th = bounds.project(model.pack(state) + step)
    return float(model.objective(model.unpack(th, state), y, wgt)[0])


def rejected(li: int, n: int, lam: float, chi2: float, target: float, kept: float, solved: bool):
    """The record and the note of a raised weight the data reject (``fit.py``, step 4)."""
    how = "its solve ended" if solved else "its linearised step lands (on the model, not solved)"
    return ({"lam": float(lam), "chi2": float(chi2), "target": float(target), "kept_lam": float(kept),
             "solved": bool(solved)},
            f"level {li} ({n}x{n}): the discrepancy weight {lam:.4g} was rejected: {how} at chi2 {chi2:.6g}, "
            f"above the {target:.6g} it was chosen for (the linearisation did not hold); the weight stays "
            f"{kept:.4g}")


def prior_operator(grid, st) -> np.ndarray:
    """The smoothness prior's matrix R over the depths (the penalty sum (Lap z / h)^2), and with
    ``albedo_prior`` over the albedos too (the integral of |grad rho|^2 over the extent, like the
    depth's independent of the spacing, under the same weight times ``albedo_prior``)."""
    h = math.sqrt(grid.hx * grid.hy)
    lap = grid.laplacian()
    R = (lap.T @ lap).toarray() / h ** 2
    a = st.albedo_weight()
    if a > 0:
        Gx, Gy = grid.gradient_ops()
        Ra = ((Gx.T @ Gx + Gy.T @ Gy).toarray() * (h * h)) * a
        R = np.block([[R, np.zeros_like(R)], [np.zeros_like(R), Ra]])
    return R
