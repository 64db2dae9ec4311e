"""One place for reports: the JSON encoder, the frame alignment, the truth matcher, the table.

* ``jsonable`` / ``dumps``: NumPy to plain JSON (NaN and inf become null); ``json_default``
  the ``default=`` hook for records that keep NaN/inf (studies' cells, applications' files).
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
from pathlib import PurePath

import numpy as np

__all__ = ["jsonable", "json_default", "dumps", "procrustes_matrix", "alignment", "match", "compare", "table",
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


def json_default(o):
    """``json.dumps(default=...)`` for what JSON lacks: NumPy arrays and scalars as plain Python
    (non-finite floats then stay NaN/Infinity, which Python's JSON reads back: for records where
    an |err|/std of inf must stay inf), paths as strings. Anything else is an error."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.bool_, np.integer, np.floating)):
        return o.item()
    if isinstance(o, PurePath):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


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


#: scalar columns of the table: (quantity, group title with unit, factor from the JSON's unit, format)
_SCALARS = (("albedo", "albedo", 1.0, ".4f"), ("specular", "specular", 1.0, ".4f"),
            ("exponent", "exponent", 1.0, ".4g"), ("area", "area (cm²)", 1e4, ".4g"),
            ("albedo_area", "albedo·area (cm²)", 1e4, ".4g"), ("extent", "extent (cm)", 1e2, ".4g"))
_LEGEND = ("σ: one standard deviation (position: norm of the three component σ; normal: rms angle).\n"
           "n/i: not identifiable from these data (why: notes in estimate.json); given: an input, "
           "not estimated; -: not modelled.")


def _num(v, spec: str) -> str:
    return "-" if v is None or not math.isfinite(float(v)) else format(float(v), spec)


def _sig(v) -> str:
    """A std with two significant digits."""
    if v is None or not math.isfinite(float(v)):
        return "-"
    return "0" if float(v) == 0.0 else format(float(v), ".2g")


def _z(v) -> str:
    if v is None:
        return "-"
    return "inf" if not math.isfinite(float(v)) else format(float(v), ".2f" if v < 10 else ".3g")


def _has_std(row: dict) -> bool:
    """Whether a ``compare`` row has a reported σ (finite, not all zero)."""
    s = row.get("std")
    if s is None:
        return False
    s = np.atleast_1d(np.asarray(s, float))
    return bool(np.all(np.isfinite(s)) and np.any(s > 0))


def _missing(p: dict, q: str) -> str:
    """Cell of a null number: n/i (the data cannot identify it) or - (not modelled)."""
    return "n/i" if q in (p.get("unidentifiable") or []) or q in (p.get("notes") or {}) else "-"


def _given(p: dict, q: str) -> bool:
    """A number that was an input (std 0 and a note saying where it came from)."""
    sd = p.get(f"{q}_std")
    s = vec(sd) if isinstance(sd, list) else np.array([np.nan if sd is None else sd], float)
    return bool((p.get("notes") or {}).get(q)) and not np.any(s > 0)


def _groups(pats: list, with_truth: bool) -> list:
    """(title, sub-headers, cells(p, rows)) of every column group the estimate reports."""
    def zc(q):
        return lambda p, r: ["-" if _given(p, q) or q not in r else _z(r[q]["z"])]

    def position(p, r):
        x = vec(p.get("position"))
        if not np.isfinite(x).all():
            return ["", _missing(p, "position"), "", "-"]
        s = vec(p.get("position_std"))
        sd = "given" if _given(p, "position") else (
            _sig(float(np.linalg.norm(s)) * 1e3) if np.isfinite(s).all() else "-")
        return [f"{v:.4f}" for v in x] + [sd]

    def normal(p, r):
        n = vec(p.get("normal"))
        if not np.isfinite(n).all():
            return ["", _missing(p, "normal"), "", "-"]
        s = p.get("normal_std")
        sd = "given" if _given(p, "normal") else (
            _sig(math.degrees(float(np.linalg.norm(vec(s))))) if s is not None else "-")
        return [f"{v:+.3f}" for v in n] + [sd]

    def scalar(q, f, spec):
        def cells(p, r):
            v, s = p.get(q), p.get(f"{q}_std")
            if v is None:
                return [_missing(p, q), ""]
            return [_num(float(v) * f, spec), "given" if _given(p, q) else
                    _sig(None if s is None else float(s) * f)]
        return cells

    def perr(p, r):
        return [_num(r["position"]["error"] * 1e3, ".3g") if "position" in r else "-"]

    groups = [("position (m)", ["x", "y", "z", "σ mm"], position)]
    if with_truth:
        groups[0] = ("position (m)", ["x", "y", "z", "σ mm", "pos err mm", "err/σ"],
                     lambda p, r: position(p, r) + perr(p, r) + zc("position")(p, r))
    if any(p.get("normal") is not None for p in pats):
        groups.append(("normal", ["x", "y", "z", "σ °"] + (["err/σ"] if with_truth else []),
                       (lambda p, r: normal(p, r) + zc("normal")(p, r)) if with_truth else normal))
    for q, title, f, spec in _SCALARS:
        if any(p.get(q) is not None for p in pats):
            c = scalar(q, f, spec)
            groups.append((title, ["value", "σ"] + (["err/σ"] if with_truth else []),
                           (lambda p, r, c=c, q=q: c(p, r) + zc(q)(p, r)) if with_truth else c))
    return groups


def table(est: dict, truth: dict | None = None, names: list | None = None,
          compact: bool | None = None, max_rows: int = 20) -> str:
    """What ``stircasadi run`` and ``stircasadi estimate`` print: one row per patch with its final
    numbers, units in the header.

    Columns: id, name, seen (visible to the camera), position x y z (m) and its σ (mm), unit
    normal and its σ (degrees), then albedo, area (cm²), albedo·area (cm²) (and the Phong lobe
    or hidden extent where reported), each with its σ; a group appears when some patch reports
    the number. With a ``truth`` (a Capture's truth group) every number also gets err/σ and the
    position its error (mm), after aligning the estimate's frame to the truth (``alignment``,
    ``match``).

    names : the scene's patch names in truth order (``Patch.name``; default ``truth["names"]``);
        a patch matched to a true one is shown under its name.
    compact : at most ``max_rows`` rows (the worst err/σ first with a truth; else hidden patches,
        then the largest position σ) and a summary line per number; default when there are more
        than 30 patches.
    """
    pats = list(est.get("patches") or [])
    if not pats:
        return "(no patches in the estimate)"
    compact = len(pats) > 30 if compact is None else compact
    with_truth = truth is not None
    names = names if names is not None else (truth or {}).get("names")
    rows_of: dict = {}
    tidx = [-1] * len(pats)
    if with_truth:
        tidx = match(est, truth)
        for r in compare(est, truth):
            if not _has_std(r):  # no σ reported: no err/σ to show (the error still is)
                r = {**r, "z": None}
            rows_of.setdefault(r["id"], {})[r["quantity"]] = r
    groups = [("patch", ["id", "name", "seen"], None)] + _groups(pats, with_truth)
    cells = []
    for k, p in enumerate(pats):
        nm = str(p.get("name") or p["id"])
        if names is not None and 0 <= tidx[k] < len(names) and names[tidx[k]]:
            nm = str(names[tidx[k]])
        r = rows_of.get(p["id"], {})
        row = [[str(p["id"]), nm, "yes" if p.get("visible", True) else "no"]]
        row += [fn(p, r) for _, _, fn in groups[1:]]
        cells.append(row)
    order = list(range(len(pats)))
    if compact and len(pats) > max_rows:
        def rank(k):
            zs = [r["z"] for r in rows_of.get(pats[k]["id"], {}).values()
                  if r["z"] is not None and not _given(pats[k], r["quantity"])]
            if with_truth:
                return (-(max(zs) if zs else -1.0),)
            s = float(np.linalg.norm(vec(pats[k].get("position_std"))))
            return (bool(pats[k].get("visible", True)), -(s if math.isfinite(s) else np.inf))
        order = sorted(order, key=rank)[:max_rows]
    lines = _layout(groups, [cells[k] for k in order])
    if len(order) < len(pats):
        lines.append(f"... {len(pats) - len(order)} more patches in estimate.json; shown: "
                     + ("the rows with the largest err/σ" if with_truth else
                        "hidden patches, then the largest position σ"))
        lines += _summary(pats, rows_of, with_truth)
    lines.append(_LEGEND)
    return "\n".join(lines)


def _layout(groups, rows) -> list[str]:
    """Two header lines (group titles over their columns, sub-headers), a rule, the rows."""
    spans = []
    for g, (title, subs, _) in enumerate(groups):
        w = [max([len(s)] + [len(r[g][c]) for r in rows]) for c, s in enumerate(subs)]
        inner = sum(w) + len(w) - 1
        if len(title) > inner:
            w[-1] += len(title) - inner
            inner = len(title)
        spans.append((title, subs, w, inner))

    def render(parts):
        return "  ".join(parts).rstrip()

    def cells(g, vals, left=False):
        _, _, w, _ = spans[g]
        return " ".join(v.ljust(x) if left else v.rjust(x) for v, x in zip(vals, w))

    top = render([t.ljust(inner) if g == 0 else t.center(inner) for g, (t, _, _, inner) in enumerate(spans)])
    sub = render([cells(g, s, left=(g == 0)) for g, (_, s, _, _) in enumerate(spans)])
    body = [render([cells(g, r[g], left=(g == 0)) for g in range(len(spans))]) for r in rows]
    return [top, sub, "-" * max(len(sub), len(top))] + body


def _std_size(p: dict, q: str) -> float:
    """A number's σ in the table's unit (position: mm; normal: degrees; others as their column)."""
    s = p.get(f"{q}_std")
    if s is None:
        return math.nan
    if q in ("position", "normal"):
        n = float(np.linalg.norm(vec(s)))
        return n * 1e3 if q == "position" else math.degrees(n)
    return float(s) * next(f for k, _, f, _ in _SCALARS if k == q)


def _summary(pats, rows_of, with_truth) -> list[str]:
    """One line per number over every patch (the compact form's complement to the rows shown)."""
    lines = []
    for q, label in [("position", "position"), ("normal", "normal")] + [(s[0], s[1]) for s in _SCALARS]:
        if not with_truth:
            label += {"position": " (σ mm)", "normal": " (σ °)"}.get(q, "")
        if with_truth:
            rs = [rows_of[p["id"]][q] for p in pats if q in rows_of.get(p["id"], {})
                  and rows_of[p["id"]][q]["error"] is not None and not _given(p, q)]
            if not rs:
                continue
            e = np.array([np.abs(r["error"]) for r in rs], float)
            scale, unit = {"position": (1e3, " mm"), "normal": (180 / math.pi, "°"),
                           **{s[0]: (s[2], "") for s in _SCALARS}}[q]
            text = f"{label}: {len(e)} estimated, rms error {np.sqrt(np.mean((e * scale) ** 2)):.3g}{unit}"
            zr = [r for r in rs if r["z"] is not None]
            if zr:
                z = np.array([r["z"] for r in zr], float)
                worst = zr[int(np.argmax(np.where(np.isfinite(z), z, 1e300)))]["id"]
                text += (f"; err/σ <= 1 for {np.mean(z <= 1):.0%}, <= 2 for {np.mean(z <= 2):.0%}, "
                         f"max {_z(float(np.max(z)))} (id {worst})")
            if len(zr) < len(rs):
                text += f"; {len(rs) - len(zr)} without a σ"
            lines.append(text)
        else:
            n_ok = sum(p.get(q) is not None for p in pats)
            n_ni = sum(q in (p.get("unidentifiable") or []) for p in pats)
            sd = [_std_size(p, q) for p in pats if p.get(q) is not None and not _given(p, q)]
            sd = np.array([s for s in sd if math.isfinite(s)])
            if n_ok or n_ni:
                lines.append(f"{label}: reported for {n_ok} of {len(pats)} patches"
                             + (f", not identifiable for {n_ni}" if n_ni else "")
                             + (f"; σ median {_sig(float(np.median(sd)))}, max {_sig(float(sd.max()))}"
                                if sd.size else ""))
    return lines


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
