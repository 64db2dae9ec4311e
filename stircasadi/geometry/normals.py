"""Normals from estimated positions: piecewise-planar fit (Fig. 11) and plane grouping.

When to use: after the positions are estimated, for scenes made of smooth surfaces.

1. Plane grouping by sequential RANSAC: repeatedly find the plane n . x = delta holding the most
   points within ``tol`` (total least squares refit on the inliers), remove them, repeat while a
   plane holds at least ``min_points``.
2. Normal of a patch = the normal of its plane group when it has one; otherwise the smallest
   principal axis of its k nearest neighbours (local PCA). Normals are oriented toward the
   camera (a visible patch faces it) or, for hidden patches, toward the centroid of the visible
   ones.

Neglects: curved surfaces are approximated by their local plane (k neighbours); patches on a
fold between two planes take the plane that holds them first.
"""
from __future__ import annotations

import numpy as np

__all__ = ["plane_groups", "estimate_normals", "initial_normals", "flat_groups"]


def _fit_plane(P: np.ndarray) -> tuple[np.ndarray, float, float]:
    c = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - c, full_matrices=False)
    n = vt[-1]
    return n, float(n @ c), float(s[-1] / np.sqrt(max(len(P), 1)))


def plane_groups(X: np.ndarray, tol: float | None = None, min_points: int = 6,
                 n_trials: int = 400, seed: int = 0, max_planes: int = 20) -> np.ndarray:
    """Label each point with its plane (0, 1, ...) or -1; sequential RANSAC, seeded."""
    X = np.asarray(X, float)
    M = len(X)
    labels = np.full(M, -1)
    if M < 3:
        return labels
    rng = np.random.default_rng(seed)
    if tol is None:
        # a fraction of the typical nearest-neighbour spacing
        d = np.linalg.norm(X[:, None] - X[None], axis=2)
        np.fill_diagonal(d, np.inf)
        tol = 0.2 * float(np.median(d.min(axis=1)))
    free = np.arange(M)
    for lab in range(max_planes):
        if len(free) < max(min_points, 3):
            break
        best = None
        P = X[free]
        for _ in range(n_trials):
            a, b, c = rng.choice(len(free), 3, replace=False)
            n = np.cross(P[b] - P[a], P[c] - P[a])
            nn = np.linalg.norm(n)
            if nn < 1e-12:
                continue
            n /= nn
            inl = np.abs((P - P[a]) @ n) < tol
            if best is None or inl.sum() > best.sum():
                best = inl
        if best is None or best.sum() < min_points:
            break
        n, delta, _ = _fit_plane(P[best])
        inl = np.abs(P @ n - delta) < tol
        if inl.sum() < min_points:
            break
        labels[free[inl]] = lab
        free = free[~inl]
    return labels


def estimate_normals(X: np.ndarray, visible: np.ndarray | None = None, camera=None,
                     labels: np.ndarray | None = None, k: int = 8) -> np.ndarray:
    """Unit normals (M, 3): plane-group normals where grouped, local PCA elsewhere; NaN when
    fewer than 3 points exist."""
    X = np.asarray(X, float)
    M = len(X)
    out = np.full((M, 3), np.nan)
    if M < 3:
        return out
    if labels is not None:
        for lab in np.unique(labels[labels >= 0]):
            idx = np.flatnonzero(labels == lab)
            n, _, _ = _fit_plane(X[idx])
            out[idx] = n
    d = np.linalg.norm(X[:, None] - X[None], axis=2)
    for i in range(M):
        if np.isfinite(out[i]).all():
            continue
        nb = np.argsort(d[i])[: min(k + 1, M)]
        if labels is not None and labels[i] >= 0:
            nb = nb[labels[nb] == labels[i]]
        if len(nb) >= 3:
            out[i], _, _ = _fit_plane(X[nb])
    vis = np.ones(M, bool) if visible is None else np.asarray(visible, bool)
    cam = np.zeros(3) if camera is None else np.asarray(camera, float)
    target = np.where(vis[:, None], cam[None, :], X[vis].mean(axis=0)[None, :] if vis.any() else cam)
    flip = np.einsum("md,md->m", out, target - X) < 0
    out[flip] *= -1
    return out


def initial_normals(X: np.ndarray, pairs: np.ndarray, camera, labels: np.ndarray | None = None,
                    min_cos: float = 0.05) -> tuple[np.ndarray, list]:
    """Starting normals for the joint fit, consistent with what the data saw.

    A patch faces the camera (it is seen) and every patch it exchanges a second bounce with
    (``pairs[k, j]``: the onsets measured d_kj). Its plane group's normal is used when it makes
    every such cosine positive (> ``min_cos``); otherwise the normalised bisector of the unit
    vectors toward the camera and toward the partners, which does. Returns (normals (M, 3),
    source per patch)."""
    X = np.asarray(X, float)
    M = len(X)
    cam = np.asarray(camera, float)
    grp = np.full((M, 3), np.nan)
    if labels is not None and M >= 3:
        for lab in np.unique(labels[labels >= 0]):
            idx = np.flatnonzero(labels == lab)
            if len(idx) >= 4:
                n, _, _ = _fit_plane(X[idx])
                grp[idx] = n
    out = np.zeros((M, 3))
    src = []
    for k in range(M):
        u_cam = cam - X[k]
        u_cam = u_cam / np.linalg.norm(u_cam)
        part = np.flatnonzero(pairs[k])
        part = part[part != k]
        U = X[part] - X[k]
        U = U / np.linalg.norm(U, axis=1)[:, None] if len(part) else np.zeros((0, 3))
        n = grp[k]
        if np.isfinite(n).all():
            n = n if n @ u_cam > 0 else -n
            if n @ u_cam > min_cos and (not len(U) or np.min(U @ n) > min_cos):
                out[k] = n
                src.append("plane fit (start)")
                continue
        b = u_cam + (U.mean(axis=0) if len(U) else 0.0)
        out[k] = b / np.linalg.norm(b)
        src.append("facing the camera and its second-bounce partners (start)")
    return out, src


def flat_groups(X: np.ndarray, pairs: np.ndarray, sigma: float, min_points: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Patches that form flat surfaces: plane groups (RANSAC, ``min_points`` or more, within
    3 ``sigma`` of their plane) none of whose members exchange a second bounce (coplanar patches
    cannot see each other). Returns (labels (M,), plane normals (M, 3) NaN outside groups, the
    plane normal's std (M,) in radians from the position std ``sigma``: the fit's smallest
    in-plane spread lambda gives sigma / sqrt(lambda))."""
    X = np.asarray(X, float)
    M = len(X)
    tol = max(3.0 * sigma, 1e-4)
    labels = plane_groups(X, tol=tol, min_points=min_points) if M >= min_points else np.full(M, -1)
    normals = np.full((M, 3), np.nan)
    std = np.full(M, np.nan)
    for lab in np.unique(labels[labels >= 0]):
        idx = np.flatnonzero(labels == lab)
        if np.asarray(pairs)[np.ix_(idx, idx)].any():
            labels[idx] = -1
            continue
        P = X[idx] - X[idx].mean(axis=0)
        _, s, vt = np.linalg.svd(P, full_matrices=False)
        normals[idx] = vt[-1]
        std[idx] = sigma / max(float(s[1]), 1e-12)   # s[1] = sqrt of the smaller in-plane scatter
    return labels, normals, std
