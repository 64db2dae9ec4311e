"""The scalable geometry stage: closed-form IPOPT Hessian and vectorised distance solve agree with
the direct formulations (CasADi's own Hessian, the dense T2 least squares); a twin experiment at
M = 60. Speed is measured in benchmarks/geometry.py (time_vs_M), not asserted here."""
import functools

import casadi as ca
import numpy as np
import pytest

from stircasadi.geometry import distances as dm
from stircasadi.geometry import embedding as em


def _scene(M, seed, noise=1e-4):
    rng = np.random.default_rng(seed)
    Z = rng.uniform(-0.5, 0.5, (M, 3)) + np.array([0, 0, 1.5])
    r = np.linalg.norm(Z, axis=1)
    D = np.linalg.norm(Z[:, None] - Z[None], axis=2)
    O = dm.forward_T2(r, D) + rng.normal(0, noise, (M, M))
    return Z, O, np.full((M, M), noise)


def _procrustes_rmse(X, Z):
    U, _, Vt = np.linalg.svd(X.T @ Z)
    return float(np.sqrt(np.mean(np.sum((X @ (U @ Vt) - Z) ** 2, axis=1))))


def test_structured_hessian_equals_casadi_hessian():
    M = 12
    Z, O, S = _scene(M, 0)
    sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
    X0, _ = em.classical_mds(sol.r, sol.D)
    I, J = np.triu_indices(M, 1)
    rng = np.random.default_rng(1)
    act = np.flatnonzero(rng.random(len(I)) < 0.3)
    act_r = np.flatnonzero(rng.random(M) < 0.5)
    R = np.arange(M)
    args = (X0, 1e-4, I, J, sol.D[I, J], sol.D_std[I, J], sol.eps[I, J], R, sol.r, sol.r_std,
            sol.r_eps, act, act_r)
    nlp, opts = em._bounded_nlp(*args)
    sig, lam = ca.MX.sym("s"), ca.MX.sym("l", nlp["g"].shape[0])
    L = sig * nlp["f"] + ca.dot(lam, nlp["g"])
    ref = ca.Function("h", [nlp["x"], sig, lam], [ca.triu(ca.hessian(L, nlp["x"])[0])])
    xv, lv = rng.normal(size=3 * M) * 10, rng.normal(size=nlp["g"].shape[0])
    H = opts["hess_lag"](xv, [], 0.7, lv).full()
    Href = ref(xv, 0.7, lv).full()
    assert np.abs(H - Href).max() <= 1e-12 * np.abs(Href).max()
    # the MX objective and constraints are the former SX ones
    nlp2, _ = em._bounded_nlp(*args, hessian="symbolic")
    a = ca.Function("a", [nlp["x"]], [nlp["f"], nlp["g"]])(xv)
    b = ca.Function("b", [nlp2["x"]], [nlp2["f"], nlp2["g"]])(xv)
    assert abs(float(a[0] - b[0])) <= 1e-12 * abs(float(b[0]))
    assert np.allclose(a[1].full(), b[1].full(), rtol=0, atol=1e-12)


def test_refine_same_positions_as_symbolic_hessian(monkeypatch):
    M = 30
    Z, O, S = _scene(M, 2)
    sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
    X0, _ = em.classical_mds(sol.r, sol.D)
    args = (X0, sol.r, sol.r_std, sol.D, sol.D_std, sol.eps, sol.r_eps)
    X_fast, info_fast = em.refine_bounded(*args)
    assert info_fast["n_constraints"] > 0  # IPOPT really ran
    monkeypatch.setattr(em, "_bounded_nlp", functools.partial(em._bounded_nlp, hessian="symbolic"))
    X_ref, info_ref = em.refine_bounded(*args)
    assert np.abs(X_fast - X_ref).max() < 1e-9
    for k in ("status", "iterations", "widen", "n_outside", "outliers", "n_constraints"):
        assert info_fast[k] == info_ref[k], k


@pytest.mark.parametrize("colocated", [True, False])
def test_solve_distances_equals_dense_T2_least_squares(colocated):
    """The per-pair Schur elimination against the dense weighted least squares over all unknowns
    (legs and every d_ij) with covariance (A^T W A)^+."""
    M = 7
    rng = np.random.default_rng(3)
    Z = rng.uniform(-0.5, 0.5, (M, 3)) + np.array([0, 0, 1.5])
    r = np.linalg.norm(Z, axis=1)
    c = r if colocated else np.linalg.norm(Z - np.array([0.3, 0.0, 0.0]), axis=1)
    D = np.linalg.norm(Z[:, None] - Z[None], axis=2)
    S = rng.uniform(0.5e-4, 2e-4, (M, M))
    O = dm.forward_T2(r, D, c) + rng.normal(0, 1, (M, M)) * S
    O[1, 4] = np.nan                      # one one-way pair
    sol = dm.solve_distances(np.arange(M), np.arange(M), O, S, colocated=colocated)
    iu, ju = np.triu_indices(M, 1)
    nl = M if colocated else 2 * M
    col = {(i, j): nl + k for k, (i, j) in enumerate(zip(iu, ju))}
    A, y, w = [], [], []
    for i in range(M):
        for j in range(M):
            if not np.isfinite(O[i, j]):
                continue
            a = np.zeros(nl + len(iu))
            a[i] += 1
            a[j if colocated else M + j] += 1
            if i != j:
                a[col[min(i, j), max(i, j)]] = 1
            A.append(a), y.append(O[i, j]), w.append(1 / S[i, j] ** 2)
    A, y, w = np.array(A), np.array(y), np.array(w)
    N = A.T @ (w[:, None] * A)
    Ninv = np.linalg.pinv(N, rcond=1e-12)
    x = Ninv @ (A.T @ (w * y))
    for (i, j), k in col.items():
        if not colocated and (i, j) == (1, 4):
            assert np.isinf(sol.eps[i, j])  # one-way onset with separate legs: not identified
            continue
        assert abs(sol.D[i, j] - x[k]) < 1e-9
        assert abs(sol.D_std[i, j] - np.sqrt(Ninv[k, k])) < 1e-6 * np.sqrt(Ninv[k, k])
    assert abs(sol.residual_chi2 - float(np.sum(w * (A @ x - y) ** 2))) < 1e-6
    if colocated:
        assert np.allclose(sol.r, x[:M], atol=1e-9)
        assert np.allclose(sol.r_std, np.sqrt(np.diag(Ninv)[:M]), rtol=1e-6)


def test_solve_distances_screen_rejects_a_late_onset():
    """A later family in place of O2_25 breaks reciprocity: both onsets of the pair are dropped
    (d unknown, not a guess); a pair far outside the triangle inequality is dropped as well."""
    M = 8
    Z, O, S = _scene(M, 4)
    O[2, 5] += 0.05
    O[1, 6] = O[6, 1] = O[1, 1] + O[6, 6] + 0.2        # d_16 > r_1 + r_6
    sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
    assert sorted(sol.rejected) == [(1, 6), (2, 5), (5, 2), (6, 1)]
    assert np.isnan(sol.D[2, 5]) and np.isinf(sol.eps[2, 5]) and np.isnan(sol.D[1, 6])
    ok = np.isfinite(sol.D)
    assert ok.sum() == M * M - 4
    Dt = np.linalg.norm(Z[:, None] - Z[None], axis=2)
    assert np.max(np.abs(sol.D[ok] - Dt[ok])) < 1e-3


def test_twin_experiment_M60():
    """Onset noise 1e-4 m: positions back to 1.5e-4 m RMSE after Procrustes (measured 6.4e-5),
    no bound left violated, refined no worse than classical MDS."""
    M = 60
    Z, O, S = _scene(M, 5)
    sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
    X0, _ = em.classical_mds(sol.r, sol.D)
    X, info = em.refine_bounded(X0, sol.r, sol.r_std, sol.D, sol.D_std, sol.eps, sol.r_eps)
    assert info["widen"] == 1.0 and info["n_outside"] == 0 and info["outliers"] == []
    assert _procrustes_rmse(X, Z) < 1.5e-4
    assert _procrustes_rmse(X, Z) <= _procrustes_rmse(X0, Z) * 1.05


def test_refine_active_set_leaves_no_bound_violated():
    """Scene M = 60, seed 11: IPOPT with only the bounds near-active at the least-squares optimum
    (the former refinement, max_active_rounds=0) leaves 4 pairs outside their eps bounds; the
    active-set loop adds them and re-solves, after which every pair and source leg is within
    widen * eps. Positions back to 1.5e-4 m RMSE (measured 8.1e-5)."""
    M = 60
    Z, O, S = _scene(M, 11)
    sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
    X0, _ = em.classical_mds(sol.r, sol.D)
    args = (X0, sol.r, sol.r_std, sol.D, sol.D_std, sol.eps, sol.r_eps)
    _, info0 = em.refine_bounded(*args, max_active_rounds=0)
    assert info0["n_outside"] == 4 and info0["active_set_rounds"] == 0 and "note" in info0
    X, info = em.refine_bounded(*args)
    assert info["status"] == "Solve_Succeeded" and info["widen"] == 1.0
    assert info["n_outside"] == 0 and info["active_set_rounds"] >= 1 and "note" not in info
    assert info["n_constraints"] >= info0["n_constraints"] + 4
    I, J = np.triu_indices(M, 1)
    tol = info["widen"] * (1 + 1e-6)
    assert np.all(np.abs(np.linalg.norm(X[I] - X[J], axis=1) - sol.D[I, J]) <= tol * sol.eps[I, J])
    assert np.all(np.abs(np.linalg.norm(X, axis=1) - sol.r) <= tol * sol.r_eps)
    assert _procrustes_rmse(X, Z) < 1.5e-4
