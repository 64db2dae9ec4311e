"""One place for reports: the JSON encoder, the frame alignment, the truth matcher, the table.

* ``jsonable`` / ``dumps``: NumPy to plain JSON (NaN and inf become null).
* ``procrustes_matrix``: the orthogonal Q (rotation or reflection: distances cannot tell a scene
  from its mirror image) aligning an estimate in the source-origin frame to a truth about the
  source; identity in the capture's frame.
* ``match``: the truth patch of each estimated patch — visible ones by id, hidden ones one-to-one
  by minimal total distance after alignment (Hungarian); leftovers get -1.
* ``compare``: per number the truth, the estimate, its std, the error and error/std (the
  measures of ``stircasadi.testing`` and of the studies).
* ``table``: what ``stircasadi run`` and ``stircasadi estimate`` print: one row per patch with its
  final numbers, units in the header, err/sigma where a truth exists; compact for large scenes.
"""
from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["jsonable", "dumps", "procrustes_matrix", "alignment", "match", "compare", "table",
           "vec", "position_rmse"]


def jsonable(x):
    """NumPy -> plain Python, NaN/inf -> None (JSON has neither)."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (float, np.floating)):
        v = float(x)
        return v if math.isfinite(v) else None
    return x


def dumps(d: dict, indent: int = 1) -> str:
    return json.dumps(jsonable(d), indent=indent)


def vec(x, n: int = 3) -> np.ndarray:
    """A JSON list (None -> NaN) as a float array."""
    if x is None:
        return np.full(n, np.nan)
    return np.array([np.nan if v is None else v for v in x], float)


def procrustes_matrix(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """Orthogonal Q minimising ||A Q - B|| over the rows finite in both (about the origin)."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    ok = np.isfinite(A).all(axis=1) & np.isfinite(B).all(axis=1)
    if ok.sum() < 2:
        return np.eye(3)
    U, _, Vt = np.linalg.svd(A[ok].T @ B[ok])
    return U @ Vt


def alignment(est: dict, truth: dict):
    """(Q, source) mapping estimate positions into the truth's frame: x -> (x - s) Q + s_true.
    Identity in the capture's frame; Procrustes on the visible patches about the source else."""
    s = vec(est.get("source_xyz"))
    s = np.zeros(3) if not np.isfinite(s).all() else s
    if est.get("frame") == "capture":
        return np.eye(3), s, s
    P = np.asarray(truth["positions"], float)
    rows = [(vec(p.get("position")), P[int(p["id"])]) for p in est["patches"]
            if p.get("visible", True) and 0 <= int(p["id"]) < len(P)]
    if len(rows) < 2:
        return np.eye(3), s, s
    A = np.array([a for a, _ in rows]) - s
    st = np.asarray(truth.get("source_xyz", np.zeros(3)), float)
    Bm = np.array([b for _, b in rows]) - st
    return procrustes_matrix(A, Bm), s, st


def match(est: dict, truth: dict) -> list[int]:
    """Truth index of each estimated patch (-1: none): visible by id, hidden one-to-one."""
    from scipy.optimize import linear_sum_assignment

    P = np.asarray(truth["positions"], float)
    tvis = np.asarray(truth.get("visible", np.ones(len(P), bool)), bool)
    Q, s, st = alignment(est, truth)
    out, hid, hx = [], [], []
    for k, p in enumerate(est["patches"]):
        if p.get("visible", True):
            i = int(p["id"])
            out.append(i if 0 <= i < len(P) else -1)
        else:
            out.append(-1)
            x = vec(p.get("position"))
            if np.isfinite(x).all():
                hid.append(k)
                hx.append((x - s) @ Q + st)
    cand = np.flatnonzero(~tvis)
    if hid and len(cand):
        C = np.linalg.norm(np.array(hx)[:, None, :] - P[cand][None], axis=2)
        r, c = linear_sum_assignment(C)
        for a, b in zip(r, c):
            out[hid[a]] = int(cand[b])
    return out


def compare(est: dict, truth: dict) -> list[dict]:
    """Per reported number: patch id, quantity, true value, estimate, std, error, error/std.

    Vectors (position, normal) give one row each with the error norm (normal: angle, radians)
    and err/std = max over components of |err| / std."""
    Q, s, st = alignment(est, truth)
    m = match(est, truth)
    P = np.asarray(truth["positions"], float)
    Tn = truth.get("normals")
    rows = []
    for k, p in enumerate(est["patches"]):
        i = m[k]
        if i < 0:
            rows.append({"id": p["id"], "quantity": "match", "true": None, "estimate": None,
                         "std": None, "error": None, "z": None})
            continue
        x = vec(p.get("position"))
        if np.isfinite(x).all():
            e = (x - s) @ Q + st - P[i]
            sd = np.sqrt(vec(p.get("position_std")) ** 2 @ (Q ** 2))
            z = float(np.max(np.abs(e) / sd)) if np.all(sd > 0) and np.isfinite(sd).all() else (
                0.0 if np.linalg.norm(e) < 1e-9 else np.inf)
            rows.append({"id": p["id"], "quantity": "position", "true": P[i], "estimate": x,
                         "std": sd, "error": float(np.linalg.norm(e)), "z": z})
        nv = vec(p.get("normal"))
        if Tn is not None and np.isfinite(nv).all():
            nv = nv @ Q
            c_ = abs(nv @ np.asarray(Tn[i])) / np.linalg.norm(nv)
            # the angle from the cross product (arccos near 1 is ill-conditioned: 1e-8 for equal vectors)
            ang = float(np.arctan2(np.linalg.norm(np.cross(nv / np.linalg.norm(nv), np.asarray(Tn[i]))), c_))
            ns = p.get("normal_std")
            sd = float(np.linalg.norm(vec(ns))) if ns is not None else np.nan
            z = ang / sd if sd > 0 and np.isfinite(sd) else (0.0 if ang < 1e-9 else np.inf)
            rows.append({"id": p["id"], "quantity": "normal", "true": Tn[i], "estimate": nv, "std": sd,
                         "error": ang, "z": z})
        for q, tk in (("albedo", "albedo"), ("area", "areas"), ("specular", "specular"),
                      ("exponent", "exponent"), ("albedo_area", None)):
            v = p.get(q)
            if v is None:
                continue
            if tk is None:
                if truth.get("albedo") is None or truth.get("areas") is None:
                    continue
                tv = float(truth["albedo"][i] * truth["areas"][i])
            elif truth.get(tk) is None:
                continue
            else:
                tv = float(np.asarray(truth[tk])[i])
            sd = p.get(f"{q}_std")
            err = float(v) - tv
            z = abs(err) / sd if sd else (0.0 if abs(err) < 1e-12 else np.inf)
            rows.append({"id": p["id"], "quantity": q, "true": tv, "estimate": float(v), "std": sd,
                         "error": err, "z": z})
    return rows


def _fmt(v, nd=4, width=10):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return f"{'-':>{width}}"
    return f"{v:>{width}.{nd}g}"


def table(est: dict, truth: dict | None = None, names: list | None = None,
          compact: bool | None = None) -> str:
    """One row per patch: position (m), normal, albedo, area (m^2), albedo x area (m^2) with
    their std; with a truth the errors and err/sigma (worst over the patch's numbers)."""
    pats = est["patches"]
    compact = len(pats) > 30 if compact is None else compact
    cmp = {}
    if truth is not None:
        for r in compare(est, truth):
            cmp.setdefault(r["id"], []).append(r)
    head = (f"{'patch':<7}{'vis':<4}{'x, y, z (m)':>30} {'+-pos (mm)':>10} {'normal dev':>10} "
            f"{'albedo':>8} {'+-':>7} {'area (m^2)':>10} {'alb*area':>9}")
    if truth is not None:
        head += f" {'pos err mm':>10} {'alb err':>8} {'worst z':>8}"
    lines = [head, "-" * len(head)]
    shown = pats if not compact else sorted(
        pats, key=lambda p: -max([r["z"] or 0 for r in cmp.get(p["id"], [])] + [0]))[:20]
    for p in shown:
        nm = (names[pats.index(p)] if names else p.get("name")) or str(p["id"])
        x = vec(p.get("position"))
        sd = vec(p.get("position_std"))
        nsd = p.get("normal_std")
        ns = f"{math.degrees(float(np.linalg.norm(vec(nsd)))):.2f} deg" if nsd is not None else "-"
        pos = " ".join(f"{v:9.4f}" for v in x) if np.isfinite(x).all() else f"{'not identified':>30}"
        line = (f"{nm:<7}{'yes' if p.get('visible', True) else 'no':<4}{pos:>30} "
                f"{_fmt(float(np.linalg.norm(sd)) * 1e3 if np.isfinite(sd).all() else None, 3)} "
                f"{ns:>10} {_fmt(p.get('albedo'), 4, 8)} {_fmt(p.get('albedo_std'), 2, 7)} "
                f"{_fmt(p.get('area'), 3, 10)} {_fmt(p.get('albedo_area'), 3, 9)}")
        if truth is not None:
            rs = cmp.get(p["id"], [])
            pe = next((r["error"] for r in rs if r["quantity"] == "position"), None)
            ae = next((r["error"] for r in rs if r["quantity"] == "albedo"), None)
            zs = [r["z"] for r in rs if r["z"] is not None]
            line += (f" {_fmt(pe * 1e3 if pe is not None else None, 3)} {_fmt(ae, 2, 8)} "
                     f"{_fmt(max(zs) if zs else None, 3, 8)}")
        lines.append(line)
    if compact and len(pats) > len(shown):
        lines.append(f"... {len(pats) - len(shown)} more patches in estimate.json (shown: the 20 with "
                     "the largest err/sigma)" if truth is not None else
                     f"... {len(pats) - len(shown)} more patches in estimate.json")
    return "\n".join(lines)


def position_rmse(est, truth) -> tuple[float, np.ndarray, np.ndarray]:
    """(RMSE over the visible patches after alignment, aligned estimated positions (M, 3), their
    true positions (M, 3); NaN rows where unmatched). ``est``: an estimate.json dict or any object
    with ``to_json_dict()`` (a ``GeometryEstimate``)."""
    d = est if isinstance(est, dict) else jsonable(est.to_json_dict())
    Q, s, st = alignment(d, truth)
    m = match(d, truth)
    P = np.asarray(truth["positions"], float)
    X = np.array([(vec(p.get("position")) - s) @ Q + st for p in d["patches"]])
    T = np.array([P[i] if i >= 0 else np.full(3, np.nan) for i in m])
    vis = np.array([bool(p.get("visible", True)) for p in d["patches"]])
    ok = vis & np.isfinite(X).all(axis=1) & np.isfinite(T).all(axis=1)
    rmse = float(np.sqrt(np.mean(np.sum((X[ok] - T[ok]) ** 2, axis=1)))) if ok.any() else float("nan")
    return rmse, X, T
