"""Pipeline: Capture + GeometryEstimate -> symbolic model -> NLP -> Estimate, and its report table.

When to use: ``estimate_reflectance(capture, geometry_estimate)`` is what ``stircasadi estimate``
and ``stircasadi run`` call after the geometry stage. It

1. builds a ``TransientModel`` on the geometry estimate (positions, normals; a missing (NaN)
   normal starts facing the camera (visible) or the visible centroid (hidden) and is estimated
   as a bounded rotation, see ``_initial_normals`` and ``settings.estimate_normals``; hidden
   patches on the anchor line or with a distance bound as large as the distance are fixed and
   flagged ambiguous, see ``_degenerate_hidden``), with the capture's impulse
   response (a Gaussian fitted to ``capture.irf``) and areas (see below);
2. declares the albedo of every patch unknown (and, for ``brdf="phong"``, specular and exponent
   of every visible patch), with initial albedos from the steady-state image:
   rho_i = pi a_i sum_k y[i, i, k] / phi (the time-integrated first bounce);
3. for every hidden patch: its position (box +-eps) when it is seen from >= 3 visible patches,
   else its two distances to the visible patches (``set_hidden_distances``), from the geometry
   stage's estimate, eps = the geometry stage's bound (at least one bin; ``constraints.hidden_eps``
   when the geometry stage gives none);
4. solves the NLP with IPOPT (or LM), computes Fisher standard deviations and flags.

Areas: the STIR identifies a hidden patch's albedo only through albedo x area. Areas come from
``areas=``, else from the geometry estimate's ``extras["areas"]``, else from the capture's truth
(simulated twins; recorded as ``areas_source = "capture truth"``), else 0.01 m^2 with an
``IdentifiabilityWarning``.
"""
from __future__ import annotations

import time
import warnings

import numpy as np

from ..brdf import Lambertian, Phong
from ..errors import IdentifiabilityWarning, ModelError
from ..irf import from_samples
from ..model import TransientModel
from .nlp import ReflectanceNLP, solve_ipopt
from .lm import solve_lm
from .result import Estimate
from .settings import EstimateSettings


def estimate_reflectance(capture, geometry_estimate=None, brdf: str = "lambertian",
                         settings: EstimateSettings | None = None, areas=None,
                         glossy_ids=None) -> Estimate:
    """Estimate BRDF parameters (and refine hidden geometry) from ``capture``.

    Parameters
    ----------
    capture : Capture with a full STIR and an impulse response (``capture.irf``).
    geometry_estimate : GeometryEstimate; None runs ``stircasadi.geometry.estimate_geometry``.
    brdf : ``"lambertian"`` or ``"phong"``.
    settings : EstimateSettings.
    areas : optional (M,) patch areas in the geometry estimate's order.
    glossy_ids : with ``brdf="phong"``, the patch ids given a Phong lobe (default: every visible
        patch). A lobe is identifiable only where the data sample it near its mirror direction;
        fitting one to every patch of a small scene is ill-posed (IPOPT may then fail, and the
        Fisher flags say which lobes the data do not see).
    """
    settings = (settings or EstimateSettings()).validate()
    if brdf not in ("lambertian", "phong"):
        raise ModelError(f"brdf must be 'lambertian' or 'phong'; got {brdf!r}.")
    if not capture.is_full:
        raise ModelError("estimate_reflectance needs a full STIR capture (n_ill, n_obs, n_bins); this "
                         "capture holds paired traces. Convert or use the geometry stage only.")
    t_geo = 0.0
    if geometry_estimate is None:
        from ..geometry import estimate_geometry

        t0 = time.perf_counter()
        geometry_estimate = estimate_geometry(capture)
        t_geo = time.perf_counter() - t0
    g = geometry_estimate
    if not g.success:
        raise ModelError("The geometry estimate did not succeed (a stage failed); its positions cannot "
                         "seed the reflectance NLP. Inspect geometry_estimate.stats.")
    t0 = time.perf_counter()
    ids = np.asarray(g.ids, int)
    M = len(ids)
    pos = np.asarray(g.positions, float)
    vis = np.asarray(g.visible, bool)
    nor = np.array(g.normals, float)
    def index(pid, what):
        hit = np.flatnonzero(ids == pid)
        if not hit.size:
            raise ModelError(f"The capture's {what} id {pid} is not in the geometry estimate (ids "
                             f"{ids.tolist()[:20]}); estimate geometry from this same capture.")
        return int(hit[0])

    ill = np.array([index(p, "illuminated") for p in capture.ill_ids()], int)
    obs = np.array([index(p, "observed") for p in capture.obs_ids()], int)
    a, a_src = _areas(areas, g, capture, pos, vis, ids)
    irf_source = "capture"
    irf_samples = capture.irf
    if irf_samples is None:  # estimate it from the first-bounce returns, as the geometry stage does
        from ..geometry.onsets import estimate_irf

        irf_samples = estimate_irf(capture)
        irf_source = "estimated from first-bounce returns"
        if irf_samples is None:
            raise ModelError("The capture has no impulse response ('irf') and none could be estimated "
                             "from first-bounce returns (no pulse is observed at its own patch). "
                             "Record the IRF in the capture (dataset 'irf').")
    irf = from_samples(irf_samples, capture.grid.bin_width)
    src = g.source_xyz if g.source_xyz is not None else (capture.source_xyz if capture.source_xyz is not None else np.zeros(3))
    cam = g.camera_xyz if g.camera_xyz is not None else (capture.camera_xyz if capture.camera_xyz is not None else src)
    hidden = np.flatnonzero(~vis)
    anchors = np.union1d(ill, obs)
    degenerate = _degenerate_hidden(g, pos, hidden, anchors, ids, settings, capture.grid.bin_width)
    nor, tilt_plan, normal_source = _initial_normals(nor, pos, vis, ids, anchors, src, cam, degenerate,
                                                     settings)
    y = capture.stir
    alb0 = np.full(M, 0.5)
    phi = 1.0
    for r, k in enumerate(ill):
        c = np.flatnonzero(obs == k)
        if c.size:
            alb0[k] = np.pi * a[k] * float(np.sum(y[r, c[0]])) / phi
    alb0 = np.clip(alb0, 0.05, 0.95)
    if brdf == "phong":
        gl = vis.copy() if glossy_ids is None else np.isin(ids, np.asarray(glossy_ids, int))
        if glossy_ids is not None and not gl.any():
            raise ModelError(f"glossy_ids {list(glossy_ids)} match no patch id ({ids.tolist()[:20]}).")
    else:
        gl = np.zeros(M, bool)
    brdfs = [Phong(alb0[k] * 0.8, 0.1, 10.0) if gl[k] else Lambertian(alb0[k]) for k in range(M)]
    K = settings.bounces or (3 if (~vis).any() else 2)
    model = TransientModel(pos, nor, a, capture.grid, irf, ill, obs, brdfs, source=src, camera=cam,
                           phi=phi, legs_included=capture.legs_included, bounces=K,
                           names=[f"{'V' if vis[k] else 'H'}{ids[k]}" for k in range(M)])
    model.ids = ids
    model.set_unknown("albedo", "all")
    if brdf == "phong":
        model.set_unknown("specular", "glossy").set_unknown("exponent", "glossy", upper=200.0)
    for k, (axis, two, lo, hi) in tilt_plan.items():
        model.set_tilt_axes([k], axis)
        model.set_unknown("tilt", [k], lower=lo, upper=hi)
        if two:
            model.set_unknown("tilt2", [k])
    eps_used = {}
    if settings.estimate_hidden_geometry and len(hidden):
        for h in hidden:
            if int(ids[h]) in degenerate:
                continue  # geometry fixed at the geometry stage's point; flagged below
            eps = _hidden_eps(g, ids[h], settings, capture.grid.bin_width)
            eps_used[int(ids[h])] = eps
            if len(anchors) >= 3:
                model.set_unknown("position", [h], lower=pos[h] - eps, upper=pos[h] + eps,
                                  scale=eps)
            elif len(anchors) == 2:
                model.set_hidden_distances(h, anchors, eps=eps)
    model.setup()
    hd = {}
    fixed = np.flatnonzero(vis)
    for h in hidden:
        if int(ids[h]) in eps_used:
            D0 = np.linalg.norm(pos[fixed] - pos[h], axis=1)
            hd[int(h)] = (fixed, D0, eps_used[int(ids[h])])
    nlp = ReflectanceNLP(model, y, settings, noise=capture.noise, hidden_distances=hd or None)
    t_model = time.perf_counter() - t0
    est = solve_ipopt(nlp) if settings.solver == "ipopt" else solve_lm(nlp)
    est.timings["geometry_s"] = t_geo
    est.timings["setup_s"] = t_model
    est.extra.update({"areas_source": a_src, "hidden_eps": eps_used, "brdf": brdf,
                      "irf": irf.describe(), "irf_source": irf_source, "frame": getattr(g, "frame", None),
                      "normal_source": {int(ids[k]): normal_source[k] for k in range(M)},
                      "degenerate_hidden": degenerate})
    for pid, why in degenerate.items():
        k = int(np.flatnonzero(ids == pid)[0])
        est.identifiable["position"][k] = False
        est.std["position"][k] = np.inf
        est.flags.append(f"hidden patch {model.names[k]} is ambiguous: {why}; its position and normal "
                         "were fixed at the geometry stage's values (not a result).")
    est.extra["geometry_estimate"] = g
    return est


def _areas(areas, g, capture, pos, vis, ids):
    M = len(ids)
    if areas is not None:
        a = np.asarray(areas, float)
        if a.shape != (M,) or np.any(a <= 0):
            raise ModelError(f"areas must be {M} positive numbers (m^2) in the geometry order; got {a.shape}.")
        return a, "given"
    ex = getattr(g, "extras", {}) or {}
    if "areas" in ex:
        return np.asarray(ex["areas"], float), "geometry estimate"
    t = capture.truth or {}
    if "areas" in t and t["areas"] is not None:
        ta = np.asarray(t["areas"], float)
        tp = np.asarray(t["positions"], float)
        tv = np.asarray(t.get("visible", np.ones(len(ta), bool)), bool)
        a = np.empty(M)
        for k in range(M):
            if vis[k] and 0 <= ids[k] < len(ta):
                a[k] = ta[ids[k]]
            else:  # hidden: the nearest hidden truth patch (frames agree up to rotation: use ranges)
                cand = np.flatnonzero(~tv) if (~tv).any() else np.arange(len(ta))
                rng_t = np.linalg.norm(tp[cand], axis=1)
                a[k] = ta[cand[np.argmin(np.abs(rng_t - np.linalg.norm(pos[k])))]]
        return a, "capture truth"
    warnings.warn("No patch areas are known (not given, not in the geometry estimate, no truth): using "
                  "0.01 m^2. Hidden albedos are then only albedo x area / 0.01.", IdentifiabilityWarning,
                  stacklevel=3)
    return np.full(M, 0.01), "default 0.01 m^2"


def _degenerate_hidden(g, pos, hidden, anchors, ids, settings, bin_width) -> dict:
    """Hidden patches whose geometry the data cannot refine: id -> reason.

    With two anchors a hidden patch is placed by its two distances (a circle about the anchor
    line); a patch on that line (no circle radius: trilateration is singular there), or one whose
    distance bound is as large as the distance itself (no third-bounce onset really seen: a
    spurious patch), is degenerate. Its geometry is fixed, not estimated, and it is flagged.
    """
    out = {}
    if len(anchors) != 2:
        return out
    a1, a2 = pos[anchors[0]], pos[anchors[1]]
    L = float(np.linalg.norm(a2 - a1))
    e = (a2 - a1) / L
    for h in hidden:
        v = pos[h] - a1
        r = float(np.linalg.norm(v - np.dot(v, e) * e))
        d = np.array([np.linalg.norm(pos[h] - a1), np.linalg.norm(pos[h] - a2)])
        eps = _hidden_eps(g, ids[h], settings, bin_width)
        if r <= 1e-6 * max(L, 1.0):
            out[int(ids[h])] = (f"it lies on the line through the anchors (distance {r:.2g} m): its "
                                "angle about that line is undefined")
        elif eps >= d.min():
            out[int(ids[h])] = (f"its distance bound ({eps:.3g} m) is not smaller than its distance to "
                                f"a visible patch ({d.min():.3g} m): it may be spurious")
    return out


def _initial_normals(nor, pos, vis, ids, anchors, src, cam, degenerate, settings):
    """Initial normals and which ones to estimate.

    Missing (NaN) normals start facing the camera (visible patches: the camera sees them) or the
    visible centroid (hidden patches: they send light to the wall). Which normals are freed is
    ``settings.estimate_normals`` (default ``"missing"``: the NaN ones). Rotation axes:

    * two anchors (flatland: the source and the two anchors span a plane holding the hidden
      patches, as the geometry stage places them): one in-plane angle about the plane's normal.
      The out-of-plane tilt of a hidden patch only scales all its paths like the albedo does
      (it sees two points), so it is not estimated; freed normals are projected into the plane.
    * two anchors, hidden patch off that plane (3-D): one angle about the normal of the plane
      through the patch and the two anchors (the component of the normal the two anchors see);
      visible patches about the (source, anchors) plane's normal.
    * three or more anchors: two angles (``tilt`` and ``tilt2`` about two orthogonal axes).

    Returns (normals (M, 3), {k: (axis, two_angles)}, [source string per patch]).
    """
    M = len(pos)
    nor = np.array(nor, float)
    missing = ~np.all(np.isfinite(nor), axis=1)
    cen = pos[vis].mean(axis=0) if vis.any() else np.zeros(3)
    for k in np.flatnonzero(missing):
        d = (cam - pos[k]) if vis[k] else (cen - pos[k])
        if np.linalg.norm(d) < 1e-9:  # a (spurious) patch at the centroid / camera: any direction
            d = (cam - pos[k]) if np.linalg.norm(cam - pos[k]) >= 1e-9 else np.array([0.0, 0.0, 1.0])
        nor[k] = d / np.linalg.norm(d)
    nor /= np.linalg.norm(nor, axis=1)[:, None]
    mode = getattr(settings, "estimate_normals", "missing")
    free = {"none": np.zeros(M, bool), "missing": missing, "hidden": missing | ~vis,
            "all": np.ones(M, bool)}[mode]
    for pid in degenerate:
        free[np.flatnonzero(ids == pid)] = False
    plane = None
    if len(anchors) == 2:
        p = np.cross(pos[anchors[0]] - src, pos[anchors[1]] - src)
        if np.linalg.norm(p) > 1e-9:
            plane = p / np.linalg.norm(p)
    plan, source = {}, []
    for k in range(M):
        if not free[k]:
            source.append(("assumed (facing the camera)" if vis[k] else "assumed (facing the visible centroid)")
                          if missing[k] else ("degenerate patch: geometry stage's" if int(ids[k]) in degenerate
                                              else "geometry stage (fixed)"))
            continue
        if len(anchors) >= 3 or plane is None:
            plan[k] = (None, True)
            source.append("estimated (two angles)")
            continue
        ax = plane
        if not vis[k] and abs(np.dot(pos[k] - src, plane)) > 1e-6 * max(np.linalg.norm(pos[k] - src), 1.0):
            q = np.cross(pos[anchors[0]] - pos[k], pos[anchors[1]] - pos[k])
            ax = q / np.linalg.norm(q)
            source.append("estimated (in-plane angle toward the anchors; out-of-plane part assumed)")
        else:
            source.append("estimated (in-plane angle, flatland)")
        n_in = nor[k] - np.dot(nor[k], ax) * ax
        if np.linalg.norm(n_in) < 1e-6:  # start normal along the axis: any in-plane start
            n_in = np.cross(ax, [0.0, 0.0, 1.0]) if abs(ax[2]) < 0.9 else np.cross(ax, [1.0, 0.0, 0.0])
        nor[k] = n_in / np.linalg.norm(n_in)
        # keep the patch facing what the data say it sees (else its paths vanish and the solver
        # can stall on a flat region): hidden -> both anchors (its third-bounce onsets), visible
        # -> the camera and the hidden patches found through it
        tg = (pos[anchors] if not vis[k] else
              np.vstack([cam[None, :]] + [pos[h][None, :] for h in np.flatnonzero(~vis)
                                          if int(ids[h]) not in degenerate]))
        lo, hi = _facing_interval(nor[k], ax, tg - pos[k])
        plan[k] = (ax, False, lo, hi)
    out = {}
    for k, v in plan.items():
        if v[0] is None:
            out[k] = (_any_perp(nor[k]), True, None, None)
        else:
            out[k] = v
    return nor, out, source


def _facing_interval(n0, ax, targets, margin_deg: float = 2.0, limit_deg: float = 80.0):
    """Bounds (radians) on the in-plane tilt a keeping cos(n(a), target) > 0 for every target.

    n(a) = cos a n0 + sin a (ax x n0); the cosine to w is |w_in| cos(a - b_w) with
    b_w = atan2(w . (ax x n0), w . n0), positive for |a - b_w| < 90 deg.
    """
    u = np.cross(ax, n0)
    lo, hi = -np.radians(limit_deg), np.radians(limit_deg)
    m = np.radians(margin_deg)
    for w in np.atleast_2d(targets):
        b = np.arctan2(np.dot(w, u), np.dot(w, n0))
        lo, hi = max(lo, b - np.pi / 2 + m), min(hi, b + np.pi / 2 - m)
    if not lo < 0.0 < hi:  # the start does not face every target: keep the default bounds
        return -np.radians(limit_deg), np.radians(limit_deg)
    return float(lo), float(hi)


def _any_perp(n):
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    v = e - np.dot(e, n) * n
    return v / np.linalg.norm(v)


def _hidden_eps(g, pid, settings, bin_width) -> float:
    """The geometry stage's bound on this hidden patch's distances (at least one bin), else
    ``constraints.hidden_eps``."""
    for b in getattr(g, "hidden_distance_bounds", []) or []:
        if int(b.get("id", -1)) == int(pid):
            e = np.asarray(b.get("eps", []), float)
            e = e[np.isfinite(e)]
            if e.size:
                return float(max(e.max(), bin_width))
    return float(max(settings.constraints.hidden_eps, bin_width))


# ---------------------------------------------------------------------- report
def _frame_alignment(P, Q, frame) -> np.ndarray:
    """Orthogonal A (rows are points: P @ A ~ Q) that takes the estimate's frame to the truth's.

    In the capture's frame (known visible points) the frames are the same: identity. In the
    source-origin frame positions are fixed only up to a rotation *or reflection* about the
    source (distances cannot tell a scene from its mirror image), so the alignment is the
    orthogonal Procrustes solution, the same one the geometry report uses; a proper-rotation-only
    fit would leave a mirrored estimate misaligned and match hidden patches to the wrong truth."""
    if frame == "capture" or len(P) < 3:
        return np.eye(3)
    from ..geometry.report import procrustes_matrix

    return procrustes_matrix(P, Q)


def report_table(estimate: Estimate, truth: dict | None = None, timings: dict | None = None) -> str:
    """Plain-text table: per patch and parameter the true value, the estimate, +-sigma, the error.

    ``truth`` is a Capture truth dict / ``Scene.truth_dict()`` (patch index = id for visible
    patches; hidden patches matched by nearest position after aligning the frames on the visible
    patches and the source). Unidentifiable values print as ``unidentifiable``; a failed solve
    prints FAILED at the top.
    """
    e = estimate
    lines = []
    head = "OK" if e.success else "FAILED (no result: the values below are not an estimate)"
    lines.append(f"Reflectance / joint NLP: {head}")
    lines.append(f"  solver {e.solver}, status '{e.status}', {e.iterations} iterations, cost {e.cost:.6g}, "
                 f"noise sigma {e.sigma:.3g} ({e.extra.get('sigma_source', '')})")
    tpos = tmatch = None
    if truth is not None:
        tpos = np.asarray(truth["positions"], float)
        pos = np.asarray(e.values["position"], float)
        vis = e.visible
        vis_ids = e.ids[vis]
        ok = vis_ids < len(tpos)
        P = np.vstack([pos[vis][ok], np.zeros((1, 3))])
        Q = np.vstack([tpos[vis_ids[ok]], np.zeros((1, 3))])
        A = _frame_alignment(P, Q, e.extra.get("frame"))
        aligned = pos @ A
        tvis = np.asarray(truth.get("visible", np.ones(len(tpos), bool)), bool)
        tmatch = match_hidden_to_truth(aligned, vis, e.ids, tpos, tvis)
    hdr = f"  {'patch':<8}{'parameter':<12}{'true':>12}{'estimate':>12}{'+-sigma':>11}{'error':>11}{'err/sig':>9}"
    lines.append(hdr)
    lines.append("  " + "-" * (len(hdr) - 2))

    def row(name, par, tv, ev, sv, ident=True):
        if not ident:
            lines.append(f"  {name:<8}{par:<12}{_f(tv):>12}{'unidentifiable':>23}")
            return
        err = ev - tv if (tv is not None and np.isfinite(tv)) else np.nan
        z = err / sv if (np.isfinite(err) and sv and np.isfinite(sv) and sv > 0) else np.nan
        lines.append(f"  {name:<8}{par:<12}{_f(tv):>12}{_f(ev):>12}{_f(sv):>11}{_f(err):>11}{_f(z, 2):>9}")

    tnor = np.asarray(truth["normals"], float) if (truth is not None and truth.get("normals") is not None) else None
    for k in range(len(e.ids)):
        nm = e.names[k]
        tk = tmatch[k] if tmatch is not None else None
        if tk is not None and tk < 0:
            lines.append(f"  {nm:<8}{'(no truth)':<12}  no true patch near this hidden patch (spurious?)")
            tk = None
        for par in ("albedo", "specular", "exponent"):
            if par != "albedo" and not e.free[par][k]:
                continue
            tv = None
            if tk is not None and par in truth and truth[par] is not None:
                tv = float(np.asarray(truth[par])[tk])
            row(nm, par, tv, float(e.values[par][k]), float(e.std[par][k]), bool(e.identifiable[par][k]))
        if e.free["position"][k]:
            sp = np.asarray(e.std["position"][k], float)
            if tk is not None:
                pe = np.asarray(e.values["position"][k]) @ A - tpos[tk]
                err = float(np.linalg.norm(pe))
            else:
                err = np.nan
            if e.identifiable["position"][k]:
                lines.append(f"  {nm:<8}{'|position|':<12}{'':>12}{'':>12}{_f(float(np.linalg.norm(sp))):>11}"
                             f"{_f(err):>11}{'':>9}   (m; error after frame alignment)")
            else:
                lines.append(f"  {nm:<8}{'position':<12}{'':>12}{'unidentifiable':>23}")
        if e.free.get("normal", np.zeros(len(e.ids), bool))[k]:
            if not e.identifiable["normal"][k]:
                lines.append(f"  {nm:<8}{'normal':<12}{'':>12}{'unidentifiable':>23}")
            else:
                sn = np.asarray(e.std["normal"][k], float)
                sdeg = float(np.degrees(np.linalg.norm(sn)))   # small-angle std of the direction
                err = np.nan
                if tk is not None and tnor is not None:
                    nv = np.asarray(e.values["normal"][k]) @ A
                    err = float(np.degrees(np.arccos(np.clip(np.dot(nv, tnor[tk]), -1.0, 1.0))))
                z = err / sdeg if (np.isfinite(err) and sdeg > 0) else np.nan
                lines.append(f"  {nm:<8}{'normal':<12}{'':>12}{'':>12}{_f(sdeg):>11}{_f(err):>11}{_f(z, 2):>9}"
                             "   (deg; angle after frame alignment)")
    if e.flags:
        lines.append("  flags:")
        lines += [f"    - {f}" for f in e.flags]
    tm = dict(e.timings)
    if timings:
        tm.update(timings)
    lines.append("  time: " + ", ".join(f"{k} {v:.3f} s" for k, v in tm.items()))
    return "\n".join(lines)


def match_hidden_to_truth(aligned, vis, ids, tpos, tvis):
    """Truth index of each estimated patch: visible by id, hidden by position (aligned frame).

    Hidden patches are matched one-to-one to the hidden truth patches by minimal total distance
    (Hungarian assignment); an estimated hidden patch left over (spurious) gets -1.
    """
    from scipy.optimize import linear_sum_assignment

    M = len(ids)
    tmatch = -np.ones(M, int)
    hid = []
    for k in range(M):
        if vis[k] and ids[k] < len(tpos):
            tmatch[k] = ids[k]
        else:
            hid.append(k)
    cand = np.flatnonzero(~tvis) if (~tvis).any() else np.arange(len(tpos))
    if hid and len(cand):
        C = np.linalg.norm(aligned[hid][:, None, :] - tpos[cand][None, :, :], axis=2)
        r, c = linear_sum_assignment(C)
        for i, j in zip(r, c):
            tmatch[hid[i]] = cand[j]
    return tmatch


def _f(v, nd=4):
    if v is None:
        return "-"
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    if not np.isfinite(v):
        return "inf" if np.isinf(v) else "-"
    return f"{v:.{nd}g}"
