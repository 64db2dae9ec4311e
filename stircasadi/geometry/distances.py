"""Distances from onsets: the forward transform T2 and its weighted least-squares inverse.

When to use: after ``onsets.second_onsets`` on a full STIR with the legs included.

Equations (T2 d = O), for visible patches i, j with source distances r_i = |s - z_i| and camera
distances c_j = |z_j - o|::

    O1_i  = r_i + c_i                    (first onset, trace (i, i))
    O2_ij = r_i + d_ij + c_j             (second onset, trace (i, j), i != j)

With a co-located source and camera (s = o) r_i = c_i. Every onset carries its std sigma; the
solution minimises sum (T2 x - O)^2 / sigma^2 over x = (legs, d). Each d_ij appears only in
O2_ij and O2_ji, so it is eliminated in closed form (Schur complement): the legs are solved
from an M x M (2M x 2M when s != o) normal matrix N, then
``d_ij = sum_e w_e (O_e - a_e . q) / W``, ``W = sum_e w_e``.

Error bound: every onset std is first widened to sqrt(sigma^2 + floor^2) (``floor``: an
allowance for onset model error; the pipeline uses 1 % of a bin). Var(d_ij) = 1/W + k^T N^+ k
(k = sum_e w_e a_e / W) is then the exact covariance of the linear estimator, and
``eps_ij = z_p * sqrt(Var(d_ij))`` with z_p the two-sided normal quantile of the confidence
``level`` (0.99 -> 2.576). The rate at which the truth falls inside +-eps is checked by
Monte Carlo in tests/test_geometry_distances.py. Pairs with no onset (no second bounce, e.g.
patches facing away) get d = NaN, eps = inf. With s != o the legs have a common null direction
(r += delta, c -= delta); d is still identified when both O2_ij and O2_ji exist.

Neglects: correlation between onsets (each is fitted on its own trace); bias of an onset
fitted with the wrong impulse response.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

from ..errors import GeometryError

__all__ = ["DistanceSolution", "forward_T2", "solve_distances", "eps_quantile"]


def eps_quantile(level: float) -> float:
    """Two-sided standard-normal quantile for confidence ``level``."""
    if not 0 < level < 1:
        raise GeometryError(f"eps confidence level must be in (0, 1); got {level!r}.")
    return float(norm.ppf(0.5 + level / 2))


def joint_bound_scale(level: float, n: int) -> float:
    """Factor that turns n per-entry bounds at ``level`` into bounds that hold jointly at
    ``level`` (Bonferroni: each at 1 - (1 - level) / n). With n = 4 900 bounds at 99 %, ~49 are
    expected to exclude the truth; scaled by 1.78 all hold together with probability >= 99 %."""
    return eps_quantile(1.0 - (1.0 - level) / max(int(n), 1)) / eps_quantile(level)


@dataclass
class DistanceSolution:
    """Patch ids, source/camera leg lengths, distance matrix and bounds."""

    ids: np.ndarray
    r: np.ndarray            # |s - z_i|
    r_std: np.ndarray
    c: np.ndarray            # |z_i - o|
    c_std: np.ndarray
    D: np.ndarray            # (M, M), NaN unknown
    D_std: np.ndarray
    eps: np.ndarray          # (M, M), inf unknown
    r_eps: np.ndarray
    level: float
    colocated: bool
    residual_chi2: float
    rejected: list = None

    def joint_bound_scale(self) -> float:
        """``joint_bound_scale`` for this solution's level and number of finite bounds (pair
        distances and source legs)."""
        n = int(np.isfinite(np.triu(self.eps, 1)).sum() + np.isfinite(self.r_eps).sum())
        return joint_bound_scale(self.level, n)


def forward_T2(r: np.ndarray, D: np.ndarray, c: np.ndarray | None = None) -> np.ndarray:
    """The onset matrix O (diagonal O1, off-diagonal O2) of legs r, c and distances D."""
    c = r if c is None else c
    O = r[:, None] + D + c[None, :]
    np.fill_diagonal(O, r + c)
    return O


def solve_distances(ill: np.ndarray, obs: np.ndarray, O: np.ndarray, S: np.ndarray,
                    colocated: bool = True, level: float = 0.99, floor: float = 0.0) -> DistanceSolution:
    """Weighted least-squares inverse of T2 with closed-form error bounds.

    Parameters
    ----------
    ill, obs : ids of the STIR rows / columns.
    O, S : (n_ill, n_obs) onsets and their std (NaN = missing).
    colocated : source and camera at the same point (r = c).
    level : confidence of eps. floor : onset model-error allowance (metres of path).
    """
    from scipy.sparse import coo_matrix

    ill, obs = np.asarray(ill), np.asarray(obs)
    ids = np.union1d(ill, obs)
    M = len(ids)
    nq = M if colocated else 2 * M
    pi, pj = np.searchsorted(ids, ill), np.searchsorted(ids, obs)   # row / column -> position
    S = np.where(np.isfinite(S) & (S > 0), np.sqrt(np.maximum(S, 0) ** 2 + floor ** 2), np.nan)
    O = np.array(O, float)
    S = np.asarray(S, float)
    PI, PJ = np.broadcast_to(pi[:, None], O.shape), np.broadcast_to(pj[None, :], O.shape)
    rejected = []
    if colocated:
        # screen: reciprocity (O2_ij = O2_ji when s = o) and the triangle inequality with the
        # source (|r_i - r_j| <= d_ij <= r_i + r_j); an onset failing either is a later family
        # (or noise) detected in place of the missing second bounce.
        row_of, col_of = np.full(M, -1), np.full(M, -1)
        row_of[pi], col_of[pj] = np.arange(len(ill)), np.arange(len(obs))
        with np.errstate(invalid="ignore"):
            # the reciprocal onset O[row of j, column of i] (NaN where either is not scanned)
            ok_t = (row_of[PJ] >= 0) & (col_of[PI] >= 0)
            Ot = np.where(ok_t, O[np.maximum(row_of[PJ], 0), np.maximum(col_of[PI], 0)], np.nan)
            St = np.where(ok_t, S[np.maximum(row_of[PJ], 0), np.maximum(col_of[PI], 0)], np.nan)
            bad = np.isfinite(Ot) & (np.abs(O - Ot) > 5.0 * np.hypot(S, St))
            # first onsets O1_i = O[row of i, column of i] for ids both illuminated and observed
            both = (row_of >= 0) & (col_of >= 0)
            O1 = np.where(both, O[np.maximum(row_of, 0), np.maximum(col_of, 0)], np.nan)
            ri, rj = O1[PI] / 2, O1[PJ] / 2
            d = O - ri - rj
            tol = 5.0 * S + 1e-9
            tri = np.isfinite(ri) & np.isfinite(rj) & ((d < np.abs(ri - rj) - tol) | (d > ri + rj + tol))
            bad = (bad | tri) & np.isfinite(O) & (PI != PJ)
        rejected = [(int(ill[x]), int(obs[y])) for x, y in zip(*np.nonzero(bad))]
        O[bad] = np.nan
    # one equation per finite onset: O_e = q[p1] + q[p2] (+ d_pair when off-diagonal)
    use = np.isfinite(O) & np.isfinite(S)
    e_i, e_j, o = PI[use], PJ[use], O[use]
    w = 1.0 / S[use] ** 2
    p1, p2 = e_i, (e_j if colocated else M + e_j)
    N = np.zeros((nq, nq))
    b = np.zeros(nq)
    for u_, v_ in ((p1, p1), (p1, p2), (p2, p1), (p2, p2)):
        np.add.at(N, (u_, v_), w)
    np.add.at(b, p1, w * o)
    np.add.at(b, p2, w * o)
    # the pair unknowns d are eliminated in closed form (Schur complement per pair)
    off = e_i != e_j
    lo_, hi_ = np.minimum(e_i[off], e_j[off]), np.maximum(e_i[off], e_j[off])
    keys, grp = np.unique(lo_ * M + hi_, return_inverse=True)
    ng = len(keys)
    gi, gj = keys // M, keys % M
    wo, oo_, q1, q2 = w[off], o[off], p1[off], p2[off]
    Wd = np.bincount(grp, wo, minlength=ng)
    so = np.bincount(grp, wo * oo_, minlength=ng)
    n_eq = np.bincount(grp, minlength=ng)
    SA = coo_matrix((np.concatenate([wo, wo]), (np.concatenate([grp, grp]), np.concatenate([q1, q2]))),
                    shape=(ng, nq)).tocsr()
    SA.sum_duplicates()
    N -= (SA.T @ SA.multiply(1.0 / Wd[:, None])).toarray()
    b -= SA.T @ (so / Wd)
    # pseudo-inverse with explicit null space
    evals, evecs = np.linalg.eigh(N)
    tol = max(evals.max(), 1e-300) * 1e-12
    good = evals > tol
    Ninv = (evecs[:, good] / evals[good]) @ evecs[:, good].T
    null = evecs[:, ~good]
    q = Ninv @ b

    def var_rows(idx, val):
        """val_g . Ninv[idx_g, idx_g] . val_g per row g (padded with zero weights); inf where
        the combination touches the null space of N (not identified)."""
        v = np.einsum("ga,gab,gb->g", val, Ninv[idx[:, :, None], idx[:, None, :]], val)
        if null.size:
            proj = np.linalg.norm(np.einsum("gak,ga->gk", null[idx], val), axis=1)
            v = np.where(proj > 1e-6 * np.maximum(np.linalg.norm(val, axis=1), 1e-300), np.inf, v)
        return v

    r = q[:M]
    cc = q[:M] if colocated else q[M:]
    eye = np.arange(nq)[:, None]
    var_q = var_rows(eye, np.ones((nq, 1)))
    r_var = var_q[:M]
    c_var = r_var if colocated else var_q[M:]
    # k_g = sum_e w_e a_e / W_g: at most 4 legs per pair, padded with zero weights
    K = max(int(np.diff(SA.indptr).max()) if ng else 1, 1)
    kidx, kval = np.zeros((ng, K), int), np.zeros((ng, K))
    slot = np.arange(SA.nnz) - np.repeat(SA.indptr[:-1], np.diff(SA.indptr))
    rowg = np.repeat(np.arange(ng), np.diff(SA.indptr))
    kidx[rowg, slot] = SA.indices
    kval[rowg, slot] = SA.data / Wd[rowg]
    resid = oo_ - q[q1] - q[q2]                          # O_e - a_e . q
    dg = np.bincount(grp, wo * resid, minlength=ng) / Wd
    vg = 1.0 / Wd + var_rows(kidx, kval)
    if not colocated:
        vg = np.where(n_eq == 1, np.inf, vg)  # one-way onset with separate legs: d not identified
    D = np.full((M, M), np.nan)
    V = np.full((M, M), np.inf)
    np.fill_diagonal(D, 0.0)
    np.fill_diagonal(V, 0.0)
    D[gi, gj] = D[gj, gi] = dg
    V[gi, gj] = V[gj, gi] = vg
    chi2 = float(np.sum(wo * (resid - dg[grp]) ** 2))
    # rows with no first onset leave r undetermined in the co-located case
    r = np.where(np.isfinite(r_var), r, np.nan)
    cc = np.where(np.isfinite(c_var), cc, np.nan)
    z = eps_quantile(level)
    Dstd = np.sqrt(V)
    eps = np.where(np.isfinite(V), z * Dstd, np.inf)
    np.fill_diagonal(eps, 0.0)
    D = np.where(np.isfinite(V), D, np.nan)
    return DistanceSolution(ids=ids, r=r, r_std=np.sqrt(r_var), c=cc, c_std=np.sqrt(c_var), D=D,
                            D_std=Dstd, eps=eps, r_eps=z * np.sqrt(r_var), level=level,
                            colocated=colocated, residual_chi2=float(chi2),
                            rejected=rejected)
