"""Compare an estimate (estimate.json schema v2, as a dict) with the truth of a known scene.

When to use
-----------
In a user's pytest suite, a study cell, a notebook: wherever an estimate must be scored against
a scene whose truth is known (``Capture.truth``, ``Scene.truth_dict()``). The estimator never
sees the truth; only this module does.

What it implements
------------------
1. **Frame.** ``frame == "capture"``: the estimate is in the truth's frame (identity).
   ``frame == "source-origin"``: distances fix the scene only up to a rotation or reflection
   about the source, so the orthogonal Procrustes solution

       Q = U V^T,   U S V^T = svd(A^T B),   A = P_est - s_est,  B = P_true - s_true

   over the visible patches matched by id maps the estimate onto the truth about the source
   (``p' = (p - s_est) Q + s_true``, normals ``n' = n Q``, covariances ``Q^T C Q``).
2. **Matching.** A visible patch keeps the capture's observed id, which indexes the truth's
   arrays. Hidden patches carry ids of their own, so they are matched one-to-one to the truth's
   hidden patches by the Hungarian assignment on aligned position distance; truth left over is
   *missed*, estimates left over are *spurious*.
3. **Per number** (position and normal components, albedo, area, albedo x area, specular,
   exponent): ``err = estimate - truth`` and ``z = |err| / std``. A number reported without a
   std (``null``) is judged as ``blind_score.py`` judges it: exact when ``|err| <= exact_tol``
   (a given input), otherwise ``z = inf`` -- an error without an error bar is unbounded. The 3-D
   distance and the normal's angle are added as ``kind="norm"`` rows (their "std" is the norm of
   the component stds, the rms error); coverage statistics use the Gaussian ``"component"``
   and ``"scalar"`` rows only.

What it neglects
----------------
The Procrustes rotation is fitted to the estimate itself, so it absorbs a little of the
visible-position error (3 of 3 M degrees of freedom): visible-position z are slightly optimistic
for few patches. Extents of hidden patches (no truth field) are not compared. The matching is
by position only; a hidden estimate with no position cannot be matched and counts as spurious.

The frame alignment and the matching are ``stircasadi.report.alignment`` and ``.match``, the
project's one implementation; this module adds the per-number rows, the covariance rotation and
the coverage semantics the tests and studies use.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import StircasadiError
from ..report import alignment, match

__all__ = ["compare", "Comparison", "EXACT_TOL"]

#: |err| at or below this (in the number's units) counts as exact when no std is reported
#: (a given input); the same threshold as ``../shared/tools/blind_score.py``.
EXACT_TOL = 1e-6
_SCALARS = ("albedo", "area", "albedo_area", "specular", "exponent")
_AXES = ("x", "y", "z")


@dataclass
class Comparison:
    """The estimate scored against the truth, one row per reported number.

    Attributes
    ----------
    frame : the estimate's frame (``"capture"`` or ``"source-origin"``).
    rotation : (3, 3) the orthogonal matrix applied about the source (identity in the capture's
        frame); ``det = -1`` is a reflection.
    matches : estimate patch id -> truth index.
    missed : truth indices of hidden patches no estimate was matched to.
    spurious : estimate ids that match no truth patch.
    success : the estimate's own verdict (``success`` in the JSON).
    rows : one dict per number: ``patch_id, truth_index, visible, quantity, component, kind
        ("component" | "scalar" | "norm"), estimate, truth, err, std, z, flagged, given``.
    n_null : numbers the estimate reports as ``null`` (not estimated / not identifiable).
    """

    frame: str
    rotation: np.ndarray
    matches: dict
    missed: list
    spurious: list
    success: bool
    rows: list = field(default_factory=list)
    n_null: int = 0

    # ------------------------------------------------------------------ selections
    def select(self, quantities=None, kinds=("component", "scalar"), visible=None,
               include_given: bool = False, unflagged_only: bool = False) -> list:
        """Rows filtered by quantity names, kinds, visibility, given-ness and flags."""
        qs = None if quantities is None else ({quantities} if isinstance(quantities, str) else set(quantities))
        out = []
        for r in self.rows:
            if qs is not None and r["quantity"] not in qs:
                continue
            if kinds is not None and r["kind"] not in kinds:
                continue
            if visible is not None and r["visible"] != visible:
                continue
            if r["given"] and not include_given:
                continue
            if unflagged_only and r["flagged"]:
                continue
            out.append(r)
        return out

    def z(self, quantities=None, **kw) -> np.ndarray:
        """|err| / std of the selected rows (``inf`` where an error has no std)."""
        return np.array([r["z"] for r in self.select(quantities, **kw)], float)

    def errors(self, quantity: str, kinds=("component", "scalar", "norm"), **kw) -> np.ndarray:
        return np.array([r["err"] for r in self.select(quantity, kinds=kinds, **kw)], float)

    # ------------------------------------------------------------------ summaries
    @property
    def finite(self) -> bool:
        """Every reported value and std is a finite number (``null`` is not a value)."""
        return not any(r["nonfinite"] for r in self.rows)

    def worst(self, n: int = 5, unflagged_only: bool = False) -> list:
        rows = self.select(kinds=("component", "scalar", "norm"), unflagged_only=unflagged_only)
        return sorted(rows, key=lambda r: -r["z"] if math.isfinite(r["z"]) else -math.inf)[:n]

    def summary(self, k: float = 4.0) -> dict:
        """Counts and rms errors a study records per cell (``k``: the sigma limit)."""
        zs = self.z()
        fin = zs[np.isfinite(zs)]
        unfl = self.z(unflagged_only=True)
        out = {
            "n_numbers": len(self.rows), "n_null": self.n_null,
            "n_nonfinite": sum(r["nonfinite"] for r in self.rows),
            "n_z": int(zs.size), "n_no_std": sum(r["std_missing"] and not r["given"] and r["kind"] != "norm" for r in self.rows),
            "max_abs_z": float(np.max(zs)) if zs.size else float("nan"),
            "frac_z_le1": float(np.mean(zs <= 1)) if zs.size else float("nan"),
            "frac_z_le2": float(np.mean(zs <= 2)) if zs.size else float("nan"),
            f"n_beyond_{k:g}sigma": int(np.sum(zs > k)),
            f"n_beyond_{k:g}sigma_unflagged": int(np.sum(unfl > k)),
            "median_abs_z": float(np.median(fin)) if fin.size else float("nan"),
            "n_matched": len(self.matches), "n_missed": len(self.missed),
            "n_spurious": len(self.spurious), "success": self.success,
        }
        for q, unit_scale, name in (("position", 1.0, "err_position_m"),
                                    ("normal", 180 / math.pi, "err_normal_deg")):
            for vis, suffix in ((True, ""), (False, "_hidden")):
                e = np.array([r["err"] for r in self.select(q, kinds=("norm",), visible=vis,
                                                           include_given=True)], float)
                out[name + suffix] = float(np.sqrt(np.mean(e ** 2)) * unit_scale) if e.size else float("nan")
        for q in _SCALARS:
            e = self.errors(q, include_given=True)
            s = np.array([r["std"] for r in self.select(q, include_given=True)], float)
            out[f"err_{q}"] = float(np.sqrt(np.mean(e ** 2))) if e.size else float("nan")
            out[f"std_{q}"] = float(np.sqrt(np.nanmean(s ** 2))) if s.size and np.isfinite(s).any() else float("nan")
        return out

    def table(self, n: int | None = None) -> str:
        """Plain-text table of the rows (the worst ``n`` by z when given)."""
        rows = self.worst(n) if n else self.rows
        lines = [f"frame {self.frame}; matched {len(self.matches)}, missed hidden {self.missed}, "
                 f"spurious {self.spurious}; success {self.success}",
                 f"{'id':>5} {'vis':>3} {'quantity':>12} {'c':>1} {'estimate':>12} {'truth':>12} "
                 f"{'err':>11} {'std':>10} {'|err|/std':>9} {'flag':>4}"]
        for r in rows:
            std = "-" if r["std_missing"] else f"{r['std']:10.3g}"
            lines.append(f"{r['patch_id']:>5} {'yes' if r['visible'] else 'no':>3} {r['quantity']:>12} "
                         f"{r['component'] or '':>1} {r['estimate']:12.6g} {r['truth']:12.6g} "
                         f"{r['err']:+11.3e} {std:>10} {r['z']:9.3g} {'yes' if r['flagged'] else '':>4}")
        return "\n".join(lines)


def _num(v) -> float:
    """A JSON number as float; ``null`` -> NaN (callers test ``is None`` first where it matters)."""
    return float("nan") if v is None else float(v)


def _truth_parts(truth, source):
    """(truth dict, source xyz) from a truth dict, a Capture or a Scene."""
    if hasattr(truth, "truth_dict"):  # Scene
        src = truth.source if source is None else source
        return truth.truth_dict(), np.asarray(src, float)
    if hasattr(truth, "truth") and hasattr(truth, "grid"):  # Capture
        if truth.truth is None:
            raise StircasadiError("The capture has no truth/ group: nothing to compare against. "
                                  "Compare with the Scene (scene.truth_dict()) instead.")
        src = source if source is not None else truth.source_xyz
        return truth.truth, np.zeros(3) if src is None else np.asarray(src, float)
    if not isinstance(truth, dict) or "positions" not in truth:
        raise StircasadiError("truth must be a truth dict (Capture.truth, Scene.truth_dict()) with "
                              f"'positions', a Capture or a Scene; got {type(truth).__name__}.")
    if source is None:
        source = truth.get("source_xyz", truth.get("source", np.zeros(3)))
    return truth, np.asarray(source, float)


def _covariance_blocks(est: dict) -> dict:
    """name -> (3, 3) blocks of the JSON covariance for position[ID] and normal[ID]."""
    cov = est.get("covariance")
    if not isinstance(cov, dict) or not cov.get("parameters") or cov.get("matrix") is None:
        return {}
    names = list(cov["parameters"])
    M = np.array([[_num(x) for x in row] for row in cov["matrix"]], float)
    index = {n: k for k, n in enumerate(names)}
    blocks = {}
    for n in names:
        if n.endswith(".x"):
            stem = n[:-2]
            ks = [index.get(f"{stem}.{a}") for a in _AXES]
            if None not in ks and M.shape[0] > max(ks):
                blocks[stem] = M[np.ix_(ks, ks)]
    return blocks


def _flagged_ids(est: dict) -> set:
    ids = set()
    for amb in est.get("ambiguities") or []:
        for pid in amb.get("patch_ids") or []:
            ids.add(int(pid))
    return ids


def compare(estimate, truth, source=None, exact_tol: float = EXACT_TOL) -> Comparison:
    """Score ``estimate`` (an estimate.json dict, an ``EstimateResult``, or a path to the file)
    against ``truth`` (a truth dict, a ``Capture`` with truth, or a ``Scene``).

    Parameters
    ----------
    source : the source position in the truth's frame; default: the Capture's or Scene's
        source, a truth dict's ``source_xyz``, else the origin (the default of every Scene).
    exact_tol : |err| up to which a number without a std counts as exact (given).
    """
    est = _as_dict(estimate)
    if est.get("format", "stircasadi.estimate") != "stircasadi.estimate":
        raise StircasadiError(f"Not an estimate.json dict: format {est.get('format')!r}.")
    tr, s_true = _truth_parts(truth, source)
    P = np.asarray(tr["positions"], float)
    N = np.asarray(tr["normals"], float) if tr.get("normals") is not None else None
    M = len(P)
    vis_true = np.asarray(tr.get("visible", np.ones(M, bool)), bool)
    frame = est.get("frame", "source-origin")
    if frame not in ("capture", "source-origin"):
        raise StircasadiError(f"estimate frame must be 'capture' or 'source-origin'; got {frame!r}.")
    # the project's one frame alignment and truth matcher (stircasadi.report)
    tr_src = {**tr, "source_xyz": s_true}
    Q, s_est, s_t = alignment(est, tr_src)
    index = match(est, tr_src)
    patches = list(est.get("patches") or [])

    identity = frame == "capture"   # no arithmetic: a NaN component stays where it is

    def to_truth(x):
        return x if identity else (x - s_est) @ Q + s_t

    matches = {int(p["id"]): int(i) for p, i in zip(patches, index) if i >= 0}
    spurious = [int(p["id"]) for p, i in zip(patches, index) if i < 0]
    missed = [int(h) for h in np.flatnonzero(~vis_true) if int(h) not in set(matches.values())]

    blocks = _covariance_blocks(est)
    flagged_all = not bool(est.get("success", False))
    flagged_ids = _flagged_ids(est)
    comp = Comparison(frame=frame, rotation=np.asarray(Q, float), matches=matches, missed=missed,
                      spurious=sorted(set(spurious)), success=not flagged_all)
    by_id = {int(p["id"]): p for p in patches}
    for pid, ti in matches.items():
        p = by_id[pid]
        flag = flagged_all or pid in flagged_ids
        _vector_rows(comp, p, pid, ti, "position", P[ti], blocks, Q, to_truth, flag, exact_tol)
        if N is not None:
            _vector_rows(comp, p, pid, ti, "normal", N[ti], blocks, Q, lambda n: n if identity else n @ Q,
                         flag, exact_tol)
        for q in _SCALARS:
            t = _truth_scalar(tr, q, ti)
            if t is None:
                continue
            if p.get(q) is None:
                comp.n_null += 1
                continue
            _add_row(comp, pid, ti, p, q, "", "scalar", _num(p[q]), t, _num(p.get(f"{q}_std")),
                     flag, exact_tol)
    return comp


def _truth_scalar(tr, q, ti):
    if q == "albedo_area":
        if tr.get("albedo") is None or tr.get("areas") is None:
            return None
        return float(np.asarray(tr["albedo"])[ti] * np.asarray(tr["areas"])[ti])
    key = {"area": "areas"}.get(q, q)
    v = tr.get(key)
    return None if v is None else float(np.asarray(v, float)[ti])


def _vector_rows(comp, p, pid, ti, q, truth_vec, blocks, Q, to_truth, flag, exact_tol):
    raw = p.get(q)
    if raw is None or len(raw) != 3 or any(v is None for v in raw):
        comp.n_null += 3
        return
    xa = to_truth(np.array([float(v) for v in raw], float))
    C = blocks.get(f"{q}[{pid}]")
    if C is None:
        s = p.get(f"{q}_std")
        s = np.array([_num(v) for v in s], float) if s is not None and len(s) == 3 else np.full(3, np.nan)
        C = np.diag(s ** 2)
    identity = np.allclose(Q, np.eye(3))
    if identity:
        sa = np.sqrt(np.abs(np.diag(C)))
    elif np.isnan(C).any():
        sa = np.full(3, np.nan)   # a missing component std spreads over the rotated axes
    else:
        sa = np.sqrt(np.clip(np.diag(Q.T @ C @ Q), 0, None))
    for k, a in enumerate(_AXES):
        _add_row(comp, pid, ti, p, q, a, "component", float(xa[k]), float(truth_vec[k]), float(sa[k]),
                 flag, exact_tol)
    if not np.isfinite(xa).all():
        return
    if q == "position":
        err = float(np.linalg.norm(xa - truth_vec))
    else:
        cosang = float(np.dot(xa, truth_vec) / max(np.linalg.norm(xa) * np.linalg.norm(truth_vec), 1e-300))
        err = float(math.acos(max(-1.0, min(1.0, cosang))))
    _add_row(comp, pid, ti, p, q, "", "norm", err, 0.0, float(np.sqrt(np.sum(sa ** 2))), flag,
             exact_tol, norm=True)


def _add_row(comp, pid, ti, p, q, c, kind, value, truth, std, flag, exact_tol, norm=False):
    """One number: err, z (see the module docstring for numbers without a std)."""
    err = value if norm else value - truth
    missing = std is None or math.isnan(std)
    nonfinite = not math.isfinite(value) or (not missing and math.isinf(std))
    if nonfinite:
        z, given = math.inf, False
    elif not missing and std > 0:
        z, given = abs(err) / std, False
    elif abs(err) <= exact_tol:
        z, given = 0.0, True
    else:
        z, given = math.inf, False
    comp.rows.append({"patch_id": pid, "truth_index": ti, "visible": bool(p.get("visible", True)),
                      "quantity": q, "component": c, "kind": kind, "estimate": value,
                      "truth": truth, "err": err, "std": float("nan") if missing else std,
                      "std_missing": bool(missing), "z": z, "flagged": bool(flag),
                      "given": bool(given), "nonfinite": bool(nonfinite)})


def _as_dict(estimate) -> dict:
    if hasattr(estimate, "to_json_dict"):
        return estimate.to_json_dict()
    if isinstance(estimate, dict):
        return estimate
    from pathlib import Path
    import json

    path = Path(estimate)
    if not path.is_file():
        raise StircasadiError(f"estimate must be an estimate.json dict, an EstimateResult or a path "
                              f"to estimate.json; {path} is not a file.")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise StircasadiError(f"{path} is not valid JSON ({exc}); is it an estimate.json?") from exc
