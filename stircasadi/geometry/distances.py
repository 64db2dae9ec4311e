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

import math
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
    ill, obs = np.asarray(ill), np.asarray(obs)
    ids = np.union1d(ill, obs)
    M = len(ids)
    pos = {int(v): k for k, v in enumerate(ids)}
    nq = M if colocated else 2 * M

    def a_vec(i, j):
        """Sparse row of T2 for the leg unknowns: {index: coefficient}."""
        a: dict = {}
        for k in (pos[i], pos[j] if colocated else M + pos[j]):
            a[k] = a.get(k, 0.0) + 1.0
        return a

    def add_outer(Nm, a, b, w):
        for p_, x_ in a.items():
            for q_, y_ in b.items():
                Nm[p_, q_] += w * x_ * y_

    def add_vec(v, a, w):
        for p_, x_ in a.items():
            v[p_] += w * x_

    def dot(a, v):
        return sum(x_ * v[p_] for p_, x_ in a.items())

    def combine(items):
        out: dict = {}
        for a, w in items:
            for p_, x_ in a.items():
                out[p_] = out.get(p_, 0.0) + w * x_
        return out

    S = np.where(np.isfinite(S) & (S > 0), np.sqrt(np.maximum(S, 0) ** 2 + floor ** 2), np.nan)
    O = np.array(O, float)
    rejected = []
    if colocated:
        # screen: reciprocity (O2_ij = O2_ji when s = o) and the triangle inequality with the
        # source (|r_i - r_j| <= d_ij <= r_i + r_j); an onset failing either is a later family
        # (or noise) detected in place of the missing second bounce.
        oi = {int(v): k for k, v in enumerate(ill)}
        oo = {int(v): k for k, v in enumerate(obs)}
        O1 = {int(i): (O[oi[int(i)], oo[int(i)]], S[oi[int(i)], oo[int(i)]])
              for i in ids if int(i) in oi and int(i) in oo}
        for x, i in enumerate(ill):
            for y, j in enumerate(obs):
                i_, j_ = int(i), int(j)
                if i_ == j_ or not np.isfinite(O[x, y]):
                    continue
                bad = False
                if j_ in oi and i_ in oo and np.isfinite(O[oi[j_], oo[i_]]):
                    o2 = O[oi[j_], oo[i_]]
                    tol = 5.0 * math.hypot(S[x, y], S[oi[j_], oo[i_]])
                    bad = abs(O[x, y] - o2) > tol
                if i_ in O1 and j_ in O1 and np.all(np.isfinite([O1[i_][0], O1[j_][0]])):
                    ri, rj = O1[i_][0] / 2, O1[j_][0] / 2
                    d = O[x, y] - ri - rj
                    tol = 5.0 * S[x, y] + 1e-9
                    bad = bad or d < abs(ri - rj) - tol or d > ri + rj + tol
                if bad:
                    rejected.append((i_, j_))
        for i_, j_ in rejected:
            O[oi[i_], oo[j_]] = np.nan
    N = np.zeros((nq, nq))
    b = np.zeros(nq)
    pair_eqs: dict = {}
    for x, i in enumerate(ill):
        for y, j in enumerate(obs):
            o, s = O[x, y], S[x, y]
            if not (np.isfinite(o) and np.isfinite(s)):
                continue
            i, j = int(i), int(j)
            if i == j:
                a = a_vec(i, j)
                w = 1.0 / s ** 2
                add_outer(N, a, a, w)
                add_vec(b, a, w * o)
            else:
                key = (min(i, j), max(i, j))
                pair_eqs.setdefault(key, []).append((a_vec(i, j), o, 1.0 / s ** 2))
    for eqs in pair_eqs.values():
        Wd = sum(w for _, _, w in eqs)
        sa = combine([(a, w) for a, _, w in eqs])
        so = sum(w * o for _, o, w in eqs)
        for a, o, w in eqs:
            add_outer(N, a, a, w)
            add_vec(b, a, w * o)
        add_outer(N, sa, sa, -1.0 / Wd)
        add_vec(b, sa, -so / Wd)
    # pseudo-inverse with explicit null space
    evals, evecs = np.linalg.eigh(N)
    tol = max(evals.max(), 1e-300) * 1e-12
    good = evals > tol
    Ninv = (evecs[:, good] / evals[good]) @ evecs[:, good].T
    null = evecs[:, ~good]
    q = Ninv @ b

    def var_of(k):
        if isinstance(k, dict):
            idx = np.array(list(k.keys()), dtype=int)
            val = np.array(list(k.values()), dtype=float)
        else:
            idx = np.flatnonzero(k)
            val = k[idx]
        if null.size and np.linalg.norm(null[idx].T @ val) > 1e-6 * max(np.linalg.norm(val), 1e-300):
            return np.inf
        return float(val @ Ninv[np.ix_(idx, idx)] @ val)

    r = q[:M]
    cc = q[:M] if colocated else q[M:]
    r_var = np.array([var_of({k: 1.0}) for k in range(M)])
    c_var = r_var if colocated else np.array([var_of({M + k: 1.0}) for k in range(M)])
    D = np.full((M, M), np.nan)
    V = np.full((M, M), np.inf)
    np.fill_diagonal(D, 0.0)
    np.fill_diagonal(V, 0.0)
    chi2 = 0.0
    for (i, j), eqs in pair_eqs.items():
        Wd = sum(w for _, _, w in eqs)
        d = sum(w * (o - dot(a, q)) for a, o, w in eqs) / Wd
        k = {p_: x_ / Wd for p_, x_ in combine([(a, w) for a, _, w in eqs]).items()}
        v = 1.0 / Wd + var_of(k)
        if len(eqs) == 1 and not colocated:
            v = np.inf  # one-way onset with separate legs: d not identified
        D[pos[i], pos[j]] = D[pos[j], pos[i]] = d
        V[pos[i], pos[j]] = V[pos[j], pos[i]] = v
        chi2 += sum(w * (o - dot(a, q) - d) ** 2 for a, o, w in eqs)
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
