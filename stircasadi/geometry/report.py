"""Estimated vs true positions, Procrustes-aligned when the estimate's frame is not the truth's."""
from __future__ import annotations

import numpy as np

__all__ = ["procrustes", "report_table", "position_rmse"]


def procrustes_matrix(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Orthogonal Q (rotation or reflection: distances cannot tell a scene from its mirror image)
    minimising ||A Q - B|| over the rows finite in both, about the origin (= the source)."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    ok = np.isfinite(A).all(axis=1) & np.isfinite(B).all(axis=1)
    U, _, Vt = np.linalg.svd(A[ok].T @ B[ok])
    return U @ Vt


def procrustes(A: np.ndarray, B: np.ndarray, about_origin: bool = True) -> np.ndarray:
    """Rotate/reflect A (about the origin = the source) onto B; returns the aligned A."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    ok = np.isfinite(A).all(axis=1) & np.isfinite(B).all(axis=1)
    ca = np.zeros(3) if about_origin else A[ok].mean(axis=0)
    cb = np.zeros(3) if about_origin else B[ok].mean(axis=0)
    return (A - ca) @ procrustes_matrix(A - ca, B - cb) + cb


def _truth_arrays(est, truth):
    P = np.asarray(truth["positions"], float)
    ids = est.ids
    vis = est.visible
    T = np.full((len(ids), 3), np.nan)
    vi = ids[vis]
    T[vis] = P[vi[vi < len(P)]] if np.all(vi < len(P)) else np.nan
    hid_true = np.flatnonzero(~np.asarray(truth.get("visible", np.ones(len(P), bool)), bool))
    # hidden: match each estimated hidden patch to the nearest unused true hidden patch
    used = set()
    for a in np.flatnonzero(~vis):
        best, bd = None, np.inf
        for h in hid_true:
            if h in used or not np.isfinite(est.positions[a]).all():
                continue
            d = np.linalg.norm(est.positions[a] - P[h])
            if d < bd:
                best, bd = h, d
        if best is not None:
            used.add(best)
            T[a] = P[best]
    return T


def position_rmse(est, truth) -> tuple[float, np.ndarray, np.ndarray]:
    """(RMSE over visible patches after alignment, aligned positions, true positions)."""
    T = _truth_arrays(est, truth)
    X = est.positions
    if est.frame != "capture":
        Xa = X @ procrustes_matrix(X[est.visible], T[est.visible])
        T = _truth_arrays(type(est)(**{**est.__dict__, "positions": Xa}), truth)
        X = Xa
    ok = est.visible & np.isfinite(X).all(1) & np.isfinite(T).all(1)
    rmse = float(np.sqrt(np.mean(np.sum((X[ok] - T[ok]) ** 2, axis=1)))) if ok.any() else float("nan")
    return rmse, X, T


def report_table(estimate, truth) -> str:
    """Plain-text table: id, visible, estimated and true position, error (mm)."""
    rmse, X, T = position_rmse(estimate, truth)
    lines = [f"frame: {estimate.frame}" + ("" if estimate.frame == "capture" else
                                           " (Procrustes-aligned to the truth about the source)"),
             f"{'id':>4} {'vis':>3} {'estimated x, y, z (m)':>30} {'true x, y, z (m)':>30} {'err mm':>8}"]
    for a, i in enumerate(estimate.ids):
        e = np.linalg.norm(X[a] - T[a]) * 1e3 if np.isfinite(X[a]).all() and np.isfinite(T[a]).all() else np.nan
        fx = " ".join(f"{v:9.4f}" for v in X[a])
        ft = " ".join(f"{v:9.4f}" for v in T[a])
        lines.append(f"{int(i):>4} {'yes' if estimate.visible[a] else 'no':>3} {fx:>30} {ft:>30} {e:8.2f}")
    lines.append(f"visible-position RMSE: {rmse * 1e3:.3f} mm")
    for amb in estimate.ambiguities:
        lines.append(f"ambiguity ({amb.get('kind')}): {amb.get('message')}")
    return "\n".join(lines)
