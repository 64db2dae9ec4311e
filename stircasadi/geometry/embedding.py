"""Structure: positions from distances (isometric embedding), refined inside the eps bounds.

When to use: after ``distances.solve_distances`` when the capture does not give the visible
points; ``direct_positions`` when it does (known wall points, calibrated ray directions).

1. Classical MDS with the source at the origin: the Gram matrix of the patch positions is
   G_ij = (r_i^2 + r_j^2 - d_ij^2) / 2 (r_i = |z_i - s|); X = V_3 Lambda_3^(1/2) from its top
   three eigenpairs. Missing d_ij are imputed from the current embedding and the step repeated.
2. Bounded-error refinement (CasADi + IPOPT)::

       min_X  sum_ij ((|x_i - x_j| - d_ij) / s_ij)^2 + sum_i ((|x_i| - r_i) / s_i)^2
              + mu |X - X0|^2                                  (gauge: rotation about s)
       s.t.   (d_ij - eps_ij)^2 <= |x_i - x_j|^2 <= (d_ij + eps_ij)^2   (and the same for r)

   i.e. the maximum-likelihood positions that stay inside every error bound. If the bounds are
   mutually infeasible they are widened (x2, reported as an ambiguity); a failed solve raises
   ``SolverError``.

The frame is fixed only up to a rotation/reflection about the source: compare by Procrustes.
Neglects: nothing beyond the distance model; with fewer than 4 non-coplanar points (plus the
source) the embedding is not unique (flagged by the caller).
"""
from __future__ import annotations

import time

import numpy as np

from ..errors import GeometryError, SolverError

__all__ = ["classical_mds", "embed", "refine_bounded", "direct_positions"]


def classical_mds(r: np.ndarray, D: np.ndarray, n_iter: int = 50, fill=None) -> tuple[np.ndarray, dict]:
    """Positions (M, 3) with the source at the origin from leg lengths r and distances D.

    ``fill``: first guess of the missing distances -- None: sqrt(r_i^2 + r_j^2) (right angle at
    the source); a float t in [0, 1]: |r_i - r_j| + t (r_i + r_j - |r_i - r_j|) (between the
    triangle bounds); or an (M, M) array."""
    r = np.asarray(r, float)
    D = np.array(D, float)
    M = len(r)
    if np.any(~np.isfinite(r)):
        raise GeometryError("Classical MDS needs every source distance r_i (first onsets); "
                            f"{int(np.sum(~np.isfinite(r)))} are missing. Give the capture's "
                            "visible points (observed_xyz) or drop those patches.")
    miss = ~np.isfinite(D)
    np.fill_diagonal(miss, False)
    Df = D.copy()
    lo_b, hi_b = np.abs(r[:, None] - r[None, :]), r[:, None] + r[None, :]
    Df = np.clip(Df, lo_b, hi_b)  # triangle inequality with the source
    if fill is None:
        Df[miss] = np.sqrt(r[:, None] ** 2 + r[None, :] ** 2)[miss]
    elif np.ndim(fill) == 0:
        Df[miss] = (lo_b + float(fill) * (hi_b - lo_b))[miss]
    else:
        Df[miss] = np.clip(np.asarray(fill, float), lo_b, hi_b)[miss]
    X = np.zeros((M, 3))
    for it in range(n_iter if miss.any() else 1):
        G = 0.5 * (r[:, None] ** 2 + r[None, :] ** 2 - Df ** 2)
        w, V = np.linalg.eigh(G)
        order = np.argsort(w)[::-1][:3]
        lam = np.clip(w[order], 0, None)
        X = np.zeros((M, 3))
        X[:, : len(order)] = V[:, order] * np.sqrt(lam)[None, :]
        if not miss.any():
            break
        Dn = np.linalg.norm(X[:, None] - X[None], axis=2)
        Dn = np.clip(Dn, np.abs(r[:, None] - r[None, :]), r[:, None] + r[None, :])
        change = np.max(np.abs(Dn[miss] - Df[miss]))
        Df[miss] = Dn[miss]
        if change < 1e-10:
            break
    G = 0.5 * (r[:, None] ** 2 + r[None, :] ** 2 - Df ** 2)
    ev = np.sort(np.linalg.eigvalsh(G))[::-1]
    info = {"eigenvalues": ev[:6].tolist(), "n_missing": int(miss.sum() // 2),
            "rank_ratio": float(ev[3] / ev[0]) if M > 3 and ev[0] > 0 else 0.0}
    return X, info


def _known_terms(r, r_std, D, D_std, eps=None, r_eps=None):
    """Index arrays of the measured terms: pairs I < J whose distance (and std, and eps when
    given) is finite, legs R whose r (and std, and r_eps) is finite; and the mask over all
    upper-triangle pairs of the ones left out."""
    iu, ju = np.triu_indices(len(r), 1)
    known = np.isfinite(D[iu, ju]) & np.isfinite(D_std[iu, ju])
    rk = np.isfinite(r) & np.isfinite(r_std)
    if eps is not None:
        known &= np.isfinite(eps[iu, ju])
    if r_eps is not None:
        rk &= np.isfinite(r_eps)
    return iu[known], ju[known], np.flatnonzero(rk), ~known


def embed(r: np.ndarray, r_std: np.ndarray, D: np.ndarray, D_std: np.ndarray,
          fills=(0.5, None, 0.0, 0.25), chi2_ok: float = 3.0) -> tuple[np.ndarray, dict]:
    """Positions from distances with missing entries: classical MDS completed from several first
    guesses of the missing distances (``fills``, see ``classical_mds``), each polished by the
    weighted least squares of ``refine_bounded``'s first step; the start with the lowest mean
    normalised squared residual (chi2 per term) wins, and the search stops at the first start
    whose chi2 is below ``chi2_ok`` (a fit consistent with the onset errors).

    Why: with whole blocks of distances missing (coplanar patches see each other under zero
    angle and have no second bounce) the completion can settle in a wrong basin from one guess
    (Fig. 13 at noise 1e-7, seed 3: MDS 0.75 m off from the right-angle guess, least squares
    stuck at 0.33 m, chi2 8e4; from the mid-bound guess 0.3 mm, then 2.4e-5 m, chi2 0.05).
    Returns (X, info) with info: n_missing, rank_ratio (of the chosen MDS), fill, chi2, starts.
    """
    M = len(r)
    I, J, R, miss = _known_terms(r, r_std, D, D_std)
    d, ds = D[I, J], np.maximum(D_std[I, J], 1e-9)
    rs = np.maximum(r_std[R], 1e-9)
    best = None
    starts = []
    for fill in (fills if miss.any() else fills[:1]):
        X0, info = classical_mds(r, D, fill=fill)
        if len(I) + len(R) >= 3 * M:
            X1, ls = _ls_refine(X0, I, J, d, ds, R, r[R], rs)
            chi2 = float(2.0 * ls.cost / max(len(I) + len(R), 1))
        else:
            X1, chi2 = X0, float("nan")
        starts.append({"fill": fill, "chi2": chi2})
        if best is None or (np.isfinite(chi2) and not chi2 >= best[2]):
            best = (X1, info, chi2, fill)
        if not np.isfinite(chi2) or chi2 < chi2_ok:
            break
    X, info, chi2, fill = best
    info = dict(info)
    info.update({"fill": fill, "chi2": chi2, "starts": starts})
    return X, info


def _ls_refine(X0, I, J, d, ds, R, r, rs, loss: str = "linear", f_scale: float = 1.0):
    """Unconstrained weighted least squares (the ML positions), sparse Jacobian; ``loss`` /
    ``f_scale`` as scipy's (a robust loss for the outlier screen)."""
    from scipy.optimize import least_squares

    M = X0.shape[0]
    npair, nr = len(I), len(R)

    def res(x):
        X = x.reshape(M, 3)
        v = X[I] - X[J]
        out = [(np.linalg.norm(v, axis=1) - d) / ds, (np.linalg.norm(X[R], axis=1) - r) / rs]
        return np.concatenate(out)

    def jac(x):
        X = x.reshape(M, 3)
        v = X[I] - X[J]
        nv = np.maximum(np.linalg.norm(v, axis=1), 1e-12)
        u = v / nv[:, None] / ds[:, None]
        rows = np.repeat(np.arange(npair), 3)
        from scipy.sparse import coo_matrix
        cols_i = (3 * I[:, None] + np.arange(3)).ravel()
        cols_j = (3 * J[:, None] + np.arange(3)).ravel()
        xr = X[R]
        nr_ = np.maximum(np.linalg.norm(xr, axis=1), 1e-12)
        ur = xr / nr_[:, None] / rs[:, None]
        rows_r = npair + np.repeat(np.arange(nr), 3)
        cols_r = (3 * R[:, None] + np.arange(3)).ravel()
        data = np.concatenate([u.ravel(), -u.ravel(), ur.ravel()])
        rr = np.concatenate([rows, rows, rows_r])
        cc = np.concatenate([cols_i, cols_j, cols_r])
        return coo_matrix((data, (rr, cc)), shape=(npair + nr, 3 * M)).tocsr()

    sol = least_squares(res, X0.ravel(), jac=jac, method="trf", x_scale="jac", max_nfev=200,
                        tr_solver="lsmr", loss=loss, f_scale=f_scale)
    return sol.x.reshape(M, 3), sol


def refine_bounded(X0: np.ndarray, r: np.ndarray, r_std: np.ndarray, D: np.ndarray,
                   D_std: np.ndarray, eps: np.ndarray, r_eps: np.ndarray,
                   max_widen: int = 2, mu: float = 1e-6, active_frac: float = 0.5,
                   outlier_z: float | None = 8.0, max_outlier_rounds: int = 3,
                   max_active_rounds: int = 5) -> tuple[np.ndarray, dict]:
    """ML positions inside the eps bounds (see the module docstring).

    Three steps: the unconstrained weighted least-squares optimum (scipy TRF, sparse Jacobian);
    an outlier screen (below); then IPOPT over an active set of bounds: first those of every
    pair (and source leg) whose residual at the least-squares optimum exceeds
    ``active_frac * eps``. Pulling those pairs inside their bounds moves the others, so a bound
    left out can end up violated (5 of 19 900 at M = 200 in benchmarks/geometry.py): after each
    successful solve every bound is checked, the violated ones are added and IPOPT is re-run
    warm-started from that solution, up to ``max_active_rounds`` times. If the enlarged set is
    infeasible the bounds are widened as for the first one. ``info['active_set_rounds']`` is the
    number of re-solves; ``info['n_outside']`` the bounds (pairs and legs) still violated at the
    end, 0 unless the round cap was hit (then ``info['note']`` says so).

    Outlier screen (``outlier_z``; None switches it off): a second onset replaced by an earlier
    family (a return via a hidden or occluded patch, seen in both O2_ij and O2_ji so that the
    reciprocity screen of ``solve_distances`` cannot catch it) gives one d_ij that no point set
    fits. If any normalised residual |(|x_i - x_j| - d_ij)| / s_ij exceeds ``outlier_z`` at the
    least-squares optimum, the positions are re-fitted with a Cauchy loss (scale outlier_z / 2),
    the pairs whose residual there still exceeds ``outlier_z`` are dropped and the plain least
    squares is solved again (up to ``max_outlier_rounds`` times). For Gaussian onset errors a
    residual beyond 8 std has probability ~1e-15 per pair, so a correct distance is essentially
    never dropped; the dropped pairs (indices into X0) are returned in ``info['outliers']``.
    """
    import casadi as ca

    t_start = time.perf_counter()
    M = X0.shape[0]
    I, J, R, _ = _known_terms(r, r_std, D, D_std, eps, r_eps)
    d, ds, de = D[I, J], np.maximum(D_std[I, J], 1e-9), eps[I, J]
    rs = np.maximum(r_std[R], 1e-9)
    X1, ls = _ls_refine(X0, I, J, d, ds, R, r[R], rs)
    outliers: list[tuple[int, int]] = []
    for _ in range(max_outlier_rounds if outlier_z is not None else 0):
        z = np.abs(np.linalg.norm(X1[I] - X1[J], axis=1) - d) / ds
        if not np.any(z > outlier_z):
            break
        Xr, _ls = _ls_refine(X1, I, J, d, ds, R, r[R], rs, loss="cauchy", f_scale=outlier_z / 2)
        zr = np.abs(np.linalg.norm(Xr[I] - Xr[J], axis=1) - d) / ds
        drop = zr > outlier_z
        if not drop.any():
            break
        outliers += list(zip(I[drop].tolist(), J[drop].tolist()))
        keep = ~drop
        I, J, d, ds, de = I[keep], J[keep], d[keep], ds[keep], de[keep]
        X1, ls = _ls_refine(Xr, I, J, d, ds, R, r[R], rs)
    res_d = np.abs(np.linalg.norm(X1[I] - X1[J], axis=1) - d)
    res_r = np.abs(np.linalg.norm(X1[R], axis=1) - r[R])
    act = res_d > active_frac * de
    act_r = res_r > active_frac * r_eps[R]
    info = {"ls_status": ls.message, "ls_nfev": int(ls.nfev), "n_pairs": int(len(I)),
            "outliers": outliers}
    if not act.any() and not act_r.any():
        info.update({"status": "bounds inactive at the least-squares optimum (no IPOPT needed)",
                     "iterations": int(ls.nfev), "widen": 1.0, "n_constraints": 0,
                     "n_outside": 0, "active_set_rounds": 0,
                     "wall_time_s": time.perf_counter() - t_start})
        return X1, info
    # decision variables: displacement from the LS optimum in units of the typical distance std
    # (values ~0.1-100, STYLE.md rule 7); constraints are normalised residuals in [-1, 1] * widen
    scale = float(np.median(ds))
    rR, reR = r[R], r_eps[R]
    act, act_r = np.flatnonzero(act), np.flatnonzero(act_r)
    x0 = np.zeros(3 * M)
    lam0 = None  # multipliers of the previous round (warm start), None for a cold start
    stats_all: list[dict] = []
    widen, n_widen, iters, rounds = 1.0, 0, 0, 0
    ipopt_opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
                  "ipopt.max_iter": 300, "ipopt.tol": 1e-8, "ipopt.max_cpu_time": 60.0}
    warm_opts = {"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-4,
                 "ipopt.warm_start_bound_push": 1e-6, "ipopt.warm_start_mult_bound_push": 1e-6}
    while True:
        # active set: IPOPT sees the bounds in act / act_r; every other bound is checked after
        # the solve and the violated ones are added for the next round
        nlp, hess_opts = _bounded_nlp(X1, scale, I, J, d, ds, de, R, rR, rs, reR, act, act_r)
        nc = len(act) + len(act_r)
        solvers = {}
        while True:
            warm = lam0 is not None
            if warm not in solvers:
                solvers[warm] = ca.nlpsol("geom_refine", "ipopt", nlp,
                                          {**ipopt_opts, **hess_opts, **(warm_opts if warm else {})})
            t0 = time.perf_counter()
            sol = solvers[warm](x0=x0, lbg=-widen * np.ones(nc), ubg=widen * np.ones(nc),
                                **({"lam_g0": lam0} if warm else {}))
            st = solvers[warm].stats()
            stats_all.append({"return_status": st.get("return_status"), "success": bool(st.get("success")),
                              "iterations": int(st.get("iter_count", 0)), "widen": widen,
                              "round": rounds, "warm_start": warm, "n_constraints": nc,
                              "wall_time_s": time.perf_counter() - t0})
            if st.get("success"):
                break
            if warm:  # a failed warm start says nothing about feasibility: retry cold first
                lam0 = None
                continue
            if n_widen >= max_widen:
                raise SolverError(
                    f"Bounded-error position refinement failed: IPOPT returned "
                    f"{st.get('return_status')!r} even with the eps bounds widened x{widen:g}. "
                    "The distance bounds are mutually inconsistent; check the onsets (missing or "
                    "mislabelled families) or raise the eps confidence level.",
                    status=st.get("return_status"), stats={"attempts": stats_all})
            widen *= 2.0
            n_widen += 1
        iters += int(st.get("iter_count", 0))
        x0 = np.array(sol["x"]).ravel()
        Xs = X1 + scale * x0.reshape(M, 3, order="F")
        tol = widen * (1 + 1e-6)
        out_d = np.abs(np.linalg.norm(Xs[I] - Xs[J], axis=1) - d) > tol * de + 1e-12
        out_r = np.abs(np.linalg.norm(Xs[R], axis=1) - rR) > tol * reR + 1e-12
        new_d = np.setdiff1d(np.flatnonzero(out_d), act)
        new_r = np.setdiff1d(np.flatnonzero(out_r), act_r)
        if (new_d.size == 0 and new_r.size == 0) or rounds >= max_active_rounds:
            break
        # next round: old multipliers carried over, 0 for the added bounds
        lg = np.array(sol["lam_g"]).ravel()
        act_n, act_rn = np.union1d(act, new_d), np.union1d(act_r, new_r)
        lam0 = np.zeros(len(act_n) + len(act_rn))
        lam0[np.searchsorted(act_n, act)] = lg[:len(act)]
        lam0[len(act_n) + np.searchsorted(act_rn, act_r)] = lg[len(act):]
        act, act_r = act_n, act_rn
        rounds += 1
    n_out = int(out_d.sum() + out_r.sum())
    info.update({"status": st.get("return_status"), "iterations": iters, "widen": widen,
                 "attempts": stats_all, "n_constraints": int(len(act) + len(act_r)),
                 "n_outside": n_out, "active_set_rounds": rounds,
                 "wall_time_s": time.perf_counter() - t_start})
    if n_out:  # the round cap was hit: say so rather than return positions as bounded
        info["note"] = (f"{n_out} bounds still violated after {rounds} active-set rounds "
                        f"(max_active_rounds={max_active_rounds})")
    return Xs, info


def _bounded_nlp(X1, scale, I, J, d, ds, de, R, r, rs, re, act, act_r, hessian: str = "structured"):
    """The IPOPT problem of ``refine_bounded`` in the displacement dX = (X - X1) / scale.

    Returns ``(nlp, options)`` for ``casadi.nlpsol``. Objective and constraints are CasADi MX
    expressions over index vectors (one graph node per vector operation, not per pair), so
    building them costs O(1) nodes whatever M. The Hessian of the Lagrangian is dense in the
    3M coordinates (every pair couples two patches) and CasADi's automatic one (SX, coloured
    forward-over-reverse) costs O(M^3) graph nodes: 12 s to build at M = 100, ~100 s at 200.
    ``hessian="structured"`` supplies it in closed form instead (the same exact Hessian, so the
    same iterates): for phi(|v|) with v = x_i - x_j,

        d2 phi / dv2 = phi'' u u^T + (phi' / |v|) (I - u u^T),   u = v / |v|,

    a 3 x 3 block B_p per pair placed at (i, i), (j, j) with + and at (i, j) with -;
    phi = sigma (|v| - d)^2 / (s^2 n) for the objective and lambda_k (|v| - d) / eps for an
    active bound. ``hessian="symbolic"`` is the former SX formulation with CasADi's Hessian
    (reference for tests; small M only).
    """
    import casadi as ca

    M = X1.shape[0]
    n_terms = max(len(I) + len(R), 1)
    if hessian == "symbolic":
        X = ca.SX.sym("dX", M, 3)
        Xm = X1 + scale * X
        dist = ca.sqrt(ca.sum2((Xm[I.tolist(), :] - Xm[J.tolist(), :]) ** 2))
        rd = ca.sqrt(ca.sum2(Xm[R.tolist(), :] ** 2))
        f = (ca.sumsqr((dist - d) / ds) + ca.sumsqr((rd - r) / rs)) / n_terms
        f = f + 1e-6 * ca.sumsqr(X)  # gauge: rotation about the source
        Ia, Ja, Ra = I[act], J[act], R[act_r]
        g = ca.vertcat((ca.sqrt(ca.sum2((Xm[Ia.tolist(), :] - Xm[Ja.tolist(), :]) ** 2)) - d[act]) / de[act],
                       (ca.sqrt(ca.sum2(Xm[Ra.tolist(), :] ** 2)) - r[act_r]) / re[act_r])
        return {"x": ca.reshape(X, -1, 1), "f": f, "g": g}, {}
    if hessian != "structured":
        raise ValueError(f"hessian must be 'structured' or 'symbolic'; got {hessian!r}")
    na, nra = len(act), len(act_r)
    x = ca.MX.sym("dX", 3 * M)                    # column-major: x[k * M + i] = dX[i, k]
    Xm = ca.DM(X1) + scale * ca.reshape(x, M, 3)
    V = Xm[I.tolist(), :] - Xm[J.tolist(), :]    # (npair, 3)
    rho = ca.sqrt(ca.sum2(V ** 2))
    Vr = Xm[R.tolist(), :]
    rr = ca.sqrt(ca.sum2(Vr ** 2))
    f = (ca.sumsqr((rho - d) / ds) + ca.sumsqr((rr - r) / rs)) / n_terms
    f = f + 1e-6 * ca.sumsqr(x)  # gauge: rotation about the source
    g = ca.vertcat((rho[act.tolist()] - d[act]) / de[act], (rr[act_r.tolist()] - r[act_r]) / re[act_r])
    nlp = {"x": x, "f": f, "g": g}

    sigma = ca.MX.sym("lam_f")
    lam = ca.MX.sym("lam_g", na + nra)
    p = ca.MX.sym("p", 0, 1)

    # objective weights: phi' / |v| = c (|v| - d) / |v|, phi'' = c with c = 2 sigma / (s^2 n)
    cf = 2.0 / (ds ** 2 * n_terms)
    cr = 2.0 / (rs ** 2 * n_terms)
    # bound multipliers scattered onto the pairs (sparse constant maps)
    Pa = ca.DM(ca.Sparsity.triplet(len(I), na, act.tolist(), list(range(na))), 1.0)
    Pr = ca.DM(ca.Sparsity.triplet(len(R), nra, act_r.tolist(), list(range(nra))), 1.0)
    lam_d = ca.densify(ca.mtimes(Pa, lam[:na] / (de[act] * rho[act.tolist()]))) if na else 0.0
    lam_r = ca.densify(ca.mtimes(Pr, lam[na:] / (re[act_r] * rr[act_r.tolist()]))) if nra else 0.0
    beta = sigma * cf * (rho - d) / rho + lam_d        # coefficient of (I - u u^T)
    alpha = sigma * cf                                 # coefficient of u u^T
    beta_r = sigma * cr * (rr - r) / rr + lam_r
    alpha_r = sigma * cr
    U, Ur = V / ca.repmat(rho, 1, 3), Vr / ca.repmat(rr, 1, 3)
    s2 = scale ** 2
    kl = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    Bp, Br = {}, {}
    for k, l in kl:
        Bp[k, l] = s2 * ((alpha - beta) * U[:, k] * U[:, l] + (beta if k == l else 0.0))
        Br[k, l] = s2 * ((alpha_r - beta_r) * Ur[:, k] * Ur[:, l] + (beta_r if k == l else 0.0))
    npair, nr = len(I), len(R)
    inc = ca.DM(ca.Sparsity.triplet(M, 2 * npair, np.concatenate([I, J]).tolist(),
                                    list(range(2 * npair))), 1.0)
    inc_r = ca.DM(ca.Sparsity.triplet(M, nr, R.tolist(), list(range(nr))), 1.0)
    vals, rows, cols = [], [], []
    ar = np.arange(M)
    for k, l in kl:  # diagonal blocks: sum over the pairs and the source leg of each patch
        dg = ca.mtimes(inc, ca.vertcat(Bp[k, l], Bp[k, l])) + ca.mtimes(inc_r, Br[k, l])
        if k == l:
            dg = dg + 2e-6 * sigma
        vals.append(ca.densify(dg))
        rows.append(k * M + ar)
        cols.append(l * M + ar)
    for k in range(3):  # off-diagonal blocks (i, j), i < j: -B_p, stored in the upper triangle
        for l in range(3):
            rw, cl = k * M + I, l * M + J
            lo_tri = rw > cl
            rw, cl = np.where(lo_tri, cl, rw), np.where(lo_tri, rw, cl)
            vals.append(-Bp[min(k, l), max(k, l)])
            rows.append(rw)
            cols.append(cl)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    order = np.lexsort((rows, cols))                   # CasADi stores nonzeros column by column
    sp = ca.Sparsity.triplet(3 * M, 3 * M, rows[order].tolist(), cols[order].tolist())
    H = ca.MX(sp, ca.vertcat(*vals)[order.tolist()])
    hess = ca.Function("nlp_hess_l", [x, p, sigma, lam], [H],
                       ["x", "p", "lam_f", "lam_g"], ["triu_hess_gamma_x_x"])
    return nlp, {"hess_lag": hess}


def direct_positions(capture, ids: np.ndarray, c: np.ndarray | None = None) -> np.ndarray | None:
    """Visible positions the capture already knows: ``observed_xyz`` / ``illuminated_xyz``, or
    camera + c_j * u_j from calibrated ray directions ``extras['ray_directions']`` (n_obs, 3).
    Returns (M, 3) for ``ids`` or None when the capture knows none of them."""
    ids = np.asarray(ids)
    out = np.full((len(ids), 3), np.nan)
    for xyz, known in ((capture.observed_xyz, capture.obs_ids()), (capture.illuminated_xyz, capture.ill_ids())):
        if xyz is not None:
            for k, i in enumerate(ids):
                hit = np.flatnonzero(known == i)
                if hit.size and not np.isfinite(out[k]).all():
                    out[k] = xyz[hit[0]]
    rays = capture.extras.get("ray_directions") if isinstance(capture.extras, dict) else None
    if rays is not None and c is not None:
        rays = np.asarray(rays, float)
        o = capture.camera_xyz if capture.camera_xyz is not None else np.zeros(3)
        obs = capture.obs_ids()
        for k, i in enumerate(ids):
            hit = np.flatnonzero(obs == i)
            if hit.size and not np.isfinite(out[k]).all() and np.isfinite(c[k]):
                u = rays[hit[0]] / np.linalg.norm(rays[hit[0]])
                out[k] = o + c[k] * u
    return out if np.isfinite(out).all(axis=1).any() else None
