"""Pipeline: Capture + GeometryEstimate -> symbolic model -> NLP -> Estimate, and its report table.

When to use: ``estimate_reflectance(capture, geometry_estimate)`` is what ``stircasadi estimate``
and ``stircasadi run`` call after the geometry stage. It

1. builds a ``TransientModel`` on the geometry estimate (positions, normals; hidden patches with
   a missing normal face the centroid of the visible patches), with the capture's impulse
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
from ..model import TransientModel, irf_from_samples
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
    cen = pos[vis].mean(axis=0) if vis.any() else np.zeros(3)
    for k in range(M):
        if not np.all(np.isfinite(nor[k])):
            d = cen - pos[k]
            nor[k] = d / np.linalg.norm(d)
    nor /= np.linalg.norm(nor, axis=1)[:, None]

    def index(pid, what):
        hit = np.flatnonzero(ids == pid)
        if not hit.size:
            raise ModelError(f"The capture's {what} id {pid} is not in the geometry estimate (ids "
                             f"{ids.tolist()[:20]}); estimate geometry from this same capture.")
        return int(hit[0])

    ill = np.array([index(p, "illuminated") for p in capture.ill_ids()], int)
    obs = np.array([index(p, "observed") for p in capture.obs_ids()], int)
    a, a_src = _areas(areas, g, capture, pos, vis, ids)
    if capture.irf is None:
        raise ModelError("The capture has no impulse response ('irf'); the model needs it to place "
                         "light in bins. Record or estimate the IRF (stircasadi.geometry.onsets.estimate_irf).")
    irf = irf_from_samples(capture.irf, capture.grid.bin_width)
    src = g.source_xyz if g.source_xyz is not None else (capture.source_xyz if capture.source_xyz is not None else np.zeros(3))
    cam = g.camera_xyz if g.camera_xyz is not None else (capture.camera_xyz if capture.camera_xyz is not None else src)
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
    hidden = np.flatnonzero(~vis)
    eps_used = {}
    if settings.estimate_hidden_geometry and len(hidden):
        anchors = np.union1d(ill, obs)
        for h in hidden:
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
                      "irf": irf.describe(), "frame": getattr(g, "frame", None)})
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
def _kabsch(P, Q):
    """Rotation R minimising ||R P - Q|| (rows are points, about the origin = the source)."""
    H = P.T @ Q
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    D = np.diag([1.0, 1.0, d])
    return Vt.T @ D @ U.T


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
        R = _kabsch(P, Q) if len(P) >= 3 else np.eye(3)
        aligned = pos @ R.T
        tvis = np.asarray(truth.get("visible", np.ones(len(tpos), bool)), bool)
        tmatch = np.empty(len(e.ids), int)
        for k in range(len(e.ids)):
            if vis[k] and e.ids[k] < len(tpos):
                tmatch[k] = e.ids[k]
            else:
                cand = np.flatnonzero(~tvis) if (~tvis).any() else np.arange(len(tpos))
                tmatch[k] = cand[np.argmin(np.linalg.norm(tpos[cand] - aligned[k], axis=1))]
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

    for k in range(len(e.ids)):
        nm = e.names[k]
        tk = tmatch[k] if tmatch is not None else None
        for par in ("albedo", "specular", "exponent"):
            if par != "albedo" and not e.free[par][k]:
                continue
            tv = None
            if truth is not None and par in truth and truth[par] is not None:
                tv = float(np.asarray(truth[par])[tk])
            row(nm, par, tv, float(e.values[par][k]), float(e.std[par][k]), bool(e.identifiable[par][k]))
        if e.free["position"][k]:
            sp = np.asarray(e.std["position"][k], float)
            if truth is not None:
                pe = np.asarray(e.values["position"][k]) @ R.T - tpos[tk]
                err = float(np.linalg.norm(pe))
            else:
                err = np.nan
            if e.identifiable["position"][k]:
                lines.append(f"  {nm:<8}{'|position|':<12}{'':>12}{'':>12}{_f(float(np.linalg.norm(sp))):>11}"
                             f"{_f(err):>11}{'':>9}   (m; error after frame alignment)")
            else:
                lines.append(f"  {nm:<8}{'position':<12}{'':>12}{'unidentifiable':>23}")
    if e.flags:
        lines.append("  flags:")
        lines += [f"    - {f}" for f in e.flags]
    tm = dict(e.timings)
    if timings:
        tm.update(timings)
    lines.append("  time: " + ", ".join(f"{k} {v:.3f} s" for k, v in tm.items()))
    return "\n".join(lines)


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
