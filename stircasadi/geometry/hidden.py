"""Hidden patches from third onsets: labeling, T3 distances and trilateration.

When to use: a capture whose traces hold returns from patches the camera cannot see.

T3: a third-bounce path pulse at visible i -> hidden k -> visible j -> camera arrives at
``T = r_i + h_k[i] + h_k[j] + c_j`` (r_i, c_j the source/camera legs, h_k[i] = |x_k - z_i|).
The *excess* e = T - r_i - c_j is h_k[i] + h_k[j]; on a diagonal trace e = 2 h_k[i].

Labeling (which onset belongs to which hidden patch):

* ``label_paper``: the paper's procedure -- in every diagonal trace the m-th earliest third
  onset is assigned to hidden patch m. It fails when the hidden patches' order differs from one
  visible patch to another (several hidden patches, near-equal path lengths).
* ``label_robust``: candidates are scored by geometric consistency. With >= 3 non-collinear
  visible patches, every choice of one onset in each of three anchor traces is trilaterated in
  3-D and the point is scored by how many traces (diagonal AND off-diagonal) hold an onset
  within tolerance of its predicted excess; with 2 visible patches every pairing of diagonal
  onsets is scored by the off-diagonal trace. The best candidates are kept greedily (a merged
  onset may serve two patches) and refined by nonlinear least squares. ``edm_rank_score``
  reports how far the completed squared-distance matrix is from rank <= 5 (3-D Euclidean).

Ambiguities are reported, never resolved silently: coplanar visible patches leave a mirror
solution (we keep the camera's side and say so); two visible patches leave a circle.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from scipy.optimize import least_squares

__all__ = ["excess_onsets", "label_paper", "label_robust", "trilaterate", "edm_rank_score",
           "HiddenResult"]


class HiddenResult(dict):
    """dict with keys positions (K,3), position_std (K,3), h (K,n_v), h_std (K,n_v),
    ambiguities (list), method, scores."""


def excess_onsets(third: dict, vis_ids, r: dict | None, c: dict | None) -> dict:
    """{(i, j): (e (n,), std (n,))} with e = T - r_i - c_j (legs removed)."""
    out = {}
    for (i, j), pulses in third.items():
        if not pulses:
            continue
        ri = 0.0 if r is None else r.get(int(i), np.nan)
        cj = 0.0 if c is None else c.get(int(j), np.nan)
        e = np.array([p["tau"] for p in pulses]) - ri - cj
        s = np.array([p["tau_std"] for p in pulses])
        ok = np.isfinite(e)
        if ok.any():
            out[(int(i), int(j))] = (e[ok], s[ok])
    return out


def edm_rank_score(points: np.ndarray) -> float:
    """sigma_6 / sigma_1 of the squared-distance matrix (0 for exact 3-D geometry)."""
    P = np.asarray(points, float)
    if len(P) < 6:
        return 0.0
    D2 = np.sum((P[:, None] - P[None]) ** 2, axis=2)
    s = np.linalg.svd(D2, compute_uv=False)
    return float(s[5] / s[0]) if s[0] > 0 else 0.0


def trilaterate(Z: np.ndarray, dist: np.ndarray, std: np.ndarray, x0: np.ndarray | None = None,
                ellipse: list | None = None):
    """Least-squares point from sphere constraints |x - z_a| = dist_a (and optional ellipsoid
    constraints (z_i, z_j, e, s): |x - z_i| + |x - z_j| = e). Returns (x, cov, cost)."""
    Z = np.asarray(Z, float)
    ellipse = ellipse or []
    if x0 is None:
        x0 = Z.mean(axis=0) + np.array([0, 0, -float(np.mean(dist))])

    def res(x):
        a = (np.linalg.norm(x - Z, axis=1) - dist) / std
        b = [(np.linalg.norm(x - zi) + np.linalg.norm(x - zj) - e) / s for zi, zj, e, s in ellipse]
        return np.concatenate([a, np.array(b)])

    sol = least_squares(res, x0, method="lm" if len(dist) + len(ellipse) >= 3 else "trf")
    J = sol.jac
    try:
        cov = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    return sol.x, cov, float(2 * sol.cost)


def _sphere3(Z, rad):
    """Both intersections of three spheres (or the closest points when they miss)."""
    p1, p2, p3 = Z
    ex = p2 - p1
    dd = np.linalg.norm(ex)
    if dd < 1e-12:
        return []
    ex /= dd
    i = ex @ (p3 - p1)
    ey = p3 - p1 - i * ex
    ne = np.linalg.norm(ey)
    if ne < 1e-9:
        return []
    ey /= ne
    ez = np.cross(ex, ey)
    j = ey @ (p3 - p1)
    x = (rad[0] ** 2 - rad[1] ** 2 + dd ** 2) / (2 * dd)
    y = (rad[0] ** 2 - rad[2] ** 2 + i ** 2 + j ** 2) / (2 * j) - i / j * x
    z2 = rad[0] ** 2 - x ** 2 - y ** 2
    z = math.sqrt(max(z2, 0.0))
    base = p1 + x * ex + y * ey
    return [base + z * ez, base - z * ez] if z > 0 else [base]


def _anchor_triples(Z: np.ndarray, n: int = 6, seed: int = 0) -> list:
    M = len(Z)
    if M < 3:
        return []
    rng = np.random.default_rng(seed)
    out = []
    a = 0
    b = int(np.argmax(np.linalg.norm(Z - Z[a], axis=1)))
    area = np.linalg.norm(np.cross(Z[b] - Z[a], Z - Z[a]), axis=1)
    c = int(np.argmax(area))
    if area[c] > 1e-9:
        out.append((a, b, c))
    for _ in range(4 * n):
        t = tuple(sorted(rng.choice(M, 3, replace=False).tolist()))
        if t in out:
            continue
        if np.linalg.norm(np.cross(Z[t[1]] - Z[t[0]], Z[t[2]] - Z[t[0]])) > 1e-6:
            out.append(t)
        if len(out) >= n:
            break
    return out


def _score(x, Z, idx, excess, tol_floor):
    """(inliers, chi2, matches) of point x against every trace's excess onsets."""
    h = np.linalg.norm(x - Z, axis=1)
    n_in, chi2, matches = 0, 0.0, []
    for (i, j), (e, s) in excess.items():
        if i not in idx or j not in idx:
            continue
        pred = h[idx[i]] + h[idx[j]]
        k = int(np.argmin(np.abs(e - pred)))
        tol = max(4.0 * s[k], tol_floor)
        if abs(e[k] - pred) < tol:
            n_in += 1
            chi2 += ((e[k] - pred) / tol) ** 2
            matches.append((i, j, e[k], s[k]))
    return n_in, chi2, matches


def _finish(points, covs, Z, vis_ids, excess, matches_all, method, amb, level_z, floor):
    K = len(points)
    nv = len(Z)
    h = np.full((K, nv), np.nan)
    hs = np.full((K, nv), np.nan)
    for k in range(K):
        x, cov = points[k], covs[k]
        dv = x - Z
        nrm = np.linalg.norm(dv, axis=1)
        u = dv / np.maximum(nrm, 1e-12)[:, None]
        h[k] = nrm
        hs[k] = np.sqrt(np.maximum(np.einsum("ad,de,ae->a", u, cov, u), 0.0)) \
            if np.all(np.isfinite(cov)) else np.inf
        for (i, j, e, s) in matches_all[k]:
            if i == j:  # a direct measurement of h[i]: e = 2 h
                a = list(vis_ids).index(i)
                h[k, a], hs[k, a] = e / 2, min(hs[k, a], s / 2) if np.isfinite(hs[k, a]) else s / 2
    pos_std = np.array([np.sqrt(np.maximum(np.diag(c), 0)) if np.all(np.isfinite(c)) else
                        np.full(3, np.inf) for c in covs]).reshape(K, 3)
    eps = level_z * np.sqrt(hs ** 2 + floor ** 2)
    return HiddenResult(positions=np.array(points).reshape(K, 3), position_std=pos_std, h=h,
                        h_std=hs, h_eps=eps, ambiguities=amb, method=method, matches=matches_all)


def _coplanar(Z: np.ndarray, tol: float = 1e-3):
    if len(Z) < 4:
        return True, None
    c = Z.mean(axis=0)
    _, s, vt = np.linalg.svd(Z - c)
    return bool(s[2] < tol * max(s[0], 1e-12)), (vt[2], float(vt[2] @ c))


def _resolve_mirror(x, Z, camera, amb, k, plane):
    n, delta = plane
    side_x = x @ n - delta
    if abs(side_x) < 1e-9:
        return x
    mirror = x - 2 * side_x * n
    side_cam = camera @ n - delta
    keep = x if np.sign(side_x) == np.sign(side_cam) or side_cam == 0 else mirror
    other = mirror if keep is x else x
    amb.append({"kind": "mirror", "patches": [k],
                "message": "The visible patches are coplanar: the hidden patch and its mirror "
                           "image through their plane explain the onsets equally well; kept the "
                           "solution on the camera's side of the plane.",
                "kept": keep.tolist(), "alternative": other.tolist()})
    return keep


def label_paper(excess: dict, Z: np.ndarray, vis_ids, n_hidden: int, level_z: float = 2.576,
                floor: float = 0.0, camera=None) -> HiddenResult:
    """The paper's labeling: m-th earliest diagonal third onset -> hidden patch m."""
    idx = {int(v): a for a, v in enumerate(vis_ids)}
    points, covs, matches = [], [], []
    amb = []
    cop, plane = _coplanar(Z)
    for m in range(n_hidden):
        d, s, used, mt = [], [], [], []
        for i in vis_ids:
            key = (int(i), int(i))
            if key in excess and len(excess[key][0]) > m:
                e, es = excess[key]
                order = np.argsort(e)
                d.append(e[order[m]] / 2)
                s.append(max(es[order[m]] / 2, 1e-9))
                used.append(idx[int(i)])
                mt.append((int(i), int(i), e[order[m]], es[order[m]]))
        if len(used) < 3:
            x, cov = np.full(3, np.nan), np.full((3, 3), np.inf)
            amb.append({"kind": "underdetermined", "patches": [m],
                        "message": f"paper labeling: hidden patch {m} has {len(used)} distances "
                                   "(< 3 visible patches); position not determined."})
        else:
            x, cov, _ = trilaterate(Z[used], np.array(d), np.array(s),
                                    x0=Z[used].mean(axis=0) + 0.1)
            if cop and plane is not None and camera is not None:
                x = _resolve_mirror(x, Z, np.asarray(camera), [], m, plane)
        points.append(x)
        covs.append(cov)
        matches.append(mt)
    return _finish(points, covs, Z, vis_ids, excess, matches, "paper", amb, level_z, floor)


def label_robust(excess: dict, Z: np.ndarray, vis_ids, n_hidden: int | None = None,
                 tol_floor: float = 0.0, level_z: float = 2.576, floor: float = 0.0,
                 camera=None, min_inlier_frac: float = 0.5, seed: int = 0) -> HiddenResult:
    """Geometrically consistent labeling (see the module docstring)."""
    vis_ids = [int(v) for v in vis_ids]
    idx = {v: a for a, v in enumerate(vis_ids)}
    nv = len(vis_ids)
    amb: list = []
    n_traces = sum(1 for (i, j) in excess if i in idx and j in idx)
    cands = []
    triples = _anchor_triples(Z, seed=seed) if nv >= 3 else []
    if triples:
        for t in triples:
            lists = [excess.get((vis_ids[a], vis_ids[a]), (np.array([]), None))[0] for a in t]
            if any(len(l) == 0 for l in lists):
                continue
            for combo in itertools.islice(itertools.product(*lists), 400):
                for x in _sphere3(Z[list(t)], np.array(combo) / 2):
                    n_in, chi2, mt = _score(x, Z, idx, excess, tol_floor)
                    cands.append((n_in, -chi2, x, mt))
    elif nv == 2:
        a, b = vis_ids
        la = excess.get((a, a), (np.array([]), None))
        lb = excess.get((b, b), (np.array([]), None))
        off = excess.get((a, b), excess.get((b, a)))
        if len(la[0]) and len(lb[0]):
            for p, q in itertools.product(range(len(la[0])), range(len(lb[0]))):
                ha, hb = la[0][p] / 2, lb[0][q] / 2
                n_in, chi2 = 2, 0.0
                mt = [(a, a, la[0][p], la[1][p]), (b, b, lb[0][q], lb[1][q])]
                if off is not None:
                    e, s = off
                    k = int(np.argmin(np.abs(e - ha - hb)))
                    tol = max(4 * math.hypot(s[k], la[1][p] / 2 + lb[1][q] / 2), tol_floor)
                    if abs(e[k] - ha - hb) < tol:
                        n_in += 1
                        chi2 += ((e[k] - ha - hb) / tol) ** 2
                        mt.append((a, b, e[k], s[k]))
                    else:
                        n_in -= 1
                # a point on the circle |x - z_a| = ha, |x - z_b| = hb, camera side
                cands.append((n_in, -chi2, (ha, hb), mt))
    cands.sort(key=lambda c: (c[0], c[1]), reverse=True)
    chosen = []
    W = max(tol_floor, 1e-6)
    for n_in, nchi, x, mt in cands:
        if n_hidden is not None and len(chosen) >= n_hidden:
            break
        if n_hidden is None and n_in < min_inlier_frac * max(n_traces, 1):
            break
        dup = False
        for _, _, y, mt2 in chosen:
            if isinstance(x, tuple):
                dup = abs(x[0] - y[0]) < W and abs(x[1] - y[1]) < W
            else:
                dup = np.linalg.norm(np.asarray(x) - np.asarray(y)) < 2 * W
                if not dup and nv >= 3:
                    cop, plane = _coplanar(Z)
                    if cop and plane is not None:
                        n, dlt = plane
                        xm = np.asarray(x) - 2 * (np.asarray(x) @ n - dlt) * n
                        dup = np.linalg.norm(xm - np.asarray(y)) < 2 * W
            if dup:
                break
        if not dup:
            chosen.append((n_in, nchi, x, mt))
    if n_hidden is not None and len(chosen) < n_hidden:
        amb.append({"kind": "missing", "patches": list(range(len(chosen), n_hidden)),
                    "message": f"only {len(chosen)} of the {n_hidden} requested hidden patches "
                               "have consistent third onsets (merged or missing onsets)."})
    points, covs, matches = [], [], []
    cop, plane = _coplanar(Z) if nv >= 3 else (True, None)
    cam = np.zeros(3) if camera is None else np.asarray(camera, float)
    for k, (n_in, nchi, x, mt) in enumerate(chosen):
        if isinstance(x, tuple):
            za, zb = Z
            ha, hb = x
            u = (zb - za) / np.linalg.norm(zb - za)
            dab = np.linalg.norm(zb - za)
            t = (ha ** 2 - hb ** 2 + dab ** 2) / (2 * dab)
            rad = math.sqrt(max(ha ** 2 - t ** 2, 0.0))
            centre = za + t * u
            v = cam - centre
            v = v - (v @ u) * u
            v = v / np.linalg.norm(v) if np.linalg.norm(v) > 1e-12 else np.cross(u, [0, 0, 1.0])
            points.append(centre + rad * v)
            covs.append(np.full((3, 3), np.inf))
            amb.append({"kind": "underdetermined", "patches": [k],
                        "message": "two visible patches give two distances per hidden patch: its "
                                   "position is a circle (centre %s, radius %.4f m, axis %s); the "
                                   "point reported is the one nearest the camera, its distances "
                                   "to the visible patches are exact." %
                                   (np.round(centre, 4).tolist(), rad, np.round(u, 4).tolist())})
        else:
            ell = [(Z[idx[i]], Z[idx[j]], e, max(s, 1e-9)) for (i, j, e, s) in mt]
            xr, cov, _ = trilaterate(Z[:0], np.zeros(0), np.ones(0), x0=np.asarray(x), ellipse=ell)
            if cop and plane is not None:
                xr = _resolve_mirror(xr, Z, cam, amb, k, plane)
            points.append(xr)
            covs.append(cov)
        matches.append(mt)
    res = _finish(points, covs, Z, vis_ids, excess, matches, "robust", amb, level_z, floor)
    if len(points) and nv >= 3:
        res["edm_rank_score"] = edm_rank_score(np.vstack([Z, res["positions"]]))
    return res
