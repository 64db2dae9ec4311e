"""What the joint model estimates, and from where it starts: every policy decision in one place.

Visible patch (an id the capture illuminates or observes):

* position — given (``observed_xyz``): fixed; calibrated ray: its range along the ray; else free
  in 3-D, with the frame's rotation about the source removed by gauge constraints;
* normal — given (``observed_normals``): fixed; else two tilt angles from the geometry stage's
  plane fit (or facing the camera), estimated from the second-bounce amplitudes;
* area — a calibrated pixel's footprint Omega r^2 / cos; declared (``priors['areas']``); else an
  unknown (second bounces identify albedo, the first bounce albedo / area);
* albedo — an unknown, starting from the steady-state first bounce rho = pi a sum_k y_ii[k] / phi.

Hidden patch: position free in 3-D (``flatland`` prior: in the plane of the source and the
visible patches), normal by tilts facing the visible centroid, albedo x area as one unknown
(third bounces identify only the product), and — with ``search.extended`` — its area as a
second unknown through the spread of a disc's returns (unresolved extents are then flagged).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..brdf import Lambertian, Phong
from ..model import TransientModel
from ..radiometry import perpendicular

__all__ = ["HiddenStart", "VisibleStart", "ModelPlan", "plan_model", "gauge_generators",
           "flatland_plane"]


@dataclass
class HiddenStart:
    """Initial values of one hidden patch."""

    position: np.ndarray
    normal: np.ndarray
    albedo_area: float = 1e-3
    area: float = 4e-4
    source: str = "search"


@dataclass
class ModelPlan:
    """A declared model with the facts the caller reports."""

    model: TransientModel
    names: list
    ids: np.ndarray
    visible: np.ndarray
    given: dict
    gauge: tuple | None
    notes: list = field(default_factory=list)
    flat: np.ndarray | None = None    # (P, 2) patch pairs of one flat group (the flatness prior)


def flatland_plane(view, positions) -> np.ndarray | None:
    """Unit normal of the plane through the source and the visible patches, or None when they do
    not span one plane (the flatland prior then cannot apply)."""
    P = np.vstack([view.source[None], positions])
    c = P.mean(axis=0)
    _, s, vt = np.linalg.svd(P - c)
    if len(P) < 3 or s[1] < 1e-9 * max(s[0], 1e-12):
        return None
    if len(s) > 2 and s[2] > 1e-6 * s[0]:
        return None
    n = vt[2].copy()
    n[np.abs(n) < 1e-12] = 0.0
    return n / np.linalg.norm(n)


def gauge_generators(view, positions, normals, blocks, x_scale, free_pos, free_tilt, model) -> np.ndarray:
    """Rows G (n_g, n_x): infinitesimal rotations about the source (about the source-camera axis
    when they differ) in the scaled unknowns, for the gauge constraints G (x - x0) = 0."""
    axes = [np.eye(3)[i] for i in range(3)]
    if not view.colocated:
        a = view.camera - view.source
        axes = [a / np.linalg.norm(a)]
    G = np.zeros((len(axes), len(blocks)))
    Bm = model.params.basis
    for r, e in enumerate(axes):
        for j, (name, k, c) in enumerate(blocks):
            if name == "position" and free_pos[k]:
                dz = np.cross(e, positions[k] - view.source)
                G[r, j] = float(Bm[k][:, c] @ dz) / x_scale[j]
            elif name in ("tilt", "tilt2") and free_tilt[k]:
                n0, ax = model.normals[k], model.tilt_axis[k]
                dn = np.cross(e, normals[k])
                d = np.cross(ax, n0) if name == "tilt" else ax
                G[r, j] = float(d @ dn) / x_scale[j]
    keep = np.linalg.norm(G, axis=1) > 0
    return G[keep]


@dataclass
class VisibleStart:
    """Initial values of the visible patches (``view.ids`` order): positions (M, 3) and their std
    (NaN where unknown), normals (NaN: face the camera), albedo / area (NaN: from the first bounce)."""

    positions: np.ndarray
    position_std: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray | None = None
    area: np.ndarray | None = None
    pairs: np.ndarray | None = None   # (M, M) bool: the data saw a second bounce between them
    gain: float | None = None         # the STIR's unit (pulse energy x detector gain), if fitted
    flat_labels: np.ndarray | None = None  # (M,) flat group of each patch (-1: none)


def _gain_start(view, X, pairs, q) -> float:
    """A starting gain: time-integrated second bounces G rho_i rho_j cos cos / (pi^2 d^2) with
    rho = 0.5, cos = 0.7; without any, first bounces G rho / (pi a) with a = 0.01 m^2."""
    y = view.capture.stir
    rows, cols = view.rows(), view.cols()
    g = []
    if pairs is not None:
        for r_, i in enumerate(rows):
            for c_, j in enumerate(cols):
                if i != j and pairs[i, j]:
                    d2 = float(np.sum((X[i] - X[j]) ** 2))
                    g.append(max(float(np.sum(y[r_, c_])), 0.0) * np.pi ** 2 * d2 / (0.25 * 0.49))
    g = [v for v in g if v > 0]
    if g:
        return float(np.median(g))
    qq = q[np.isfinite(q) & (q > 0)]
    return float(np.median(qq) * 0.01 / 0.5) if len(qq) else 1.0


def plan_model(view, geo, settings, hidden: list, brdf: str = "lambertian",
               bounces: int | None = None, fixed_visible: bool = False,
               extended=None, symbolic: bool = True) -> ModelPlan:
    """Declare the joint model for the capture ``view``, the visible start ``geo``
    (``VisibleStart``) and the hidden starts ``hidden``. ``fixed_visible``: every visible number
    stays at its start (the quick test of a hidden candidate); ``extended``: which hidden
    patches are discs whose area is an unknown — True/False for all, or a set of their indices
    in ``hidden`` (default ``settings.search.extended``). ``brdf``: "lambertian", "phong" (every
    visible patch modified Phong) or a boolean mask of the glossy visible patches. ``symbolic``:
    False sets the model up without its CasADi graph (a probe: ``model.simulate`` only)."""
    extended = settings.search.extended if extended is None else extended
    ids = np.asarray(view.ids, int)
    M = len(ids)
    Hn = len(hidden)
    X = np.asarray(geo.positions[:M], float)
    N0 = np.asarray(geo.normals[:M], float).copy()
    miss = ~np.isfinite(N0).all(axis=1)
    for k in np.flatnonzero(miss):
        d = view.camera - X[k]
        N0[k] = d / np.linalg.norm(d)
    given_n = np.isfinite(view.known_normals).all(axis=1)
    N0[given_n] = view.known_normals[given_n]
    pri = view.priors
    areas_decl = pri.get("areas", {}) or {}
    a0 = np.full(M + Hn, 0.01)
    given_area = np.zeros(M + Hn, bool)
    for k, i in enumerate(ids):
        if int(i) in areas_decl:
            a0[k] = areas_decl[int(i)]
            given_area[k] = True
    foot = np.isfinite(view.solid_angle)
    if foot.any():
        los = view.camera - X
        r = np.linalg.norm(los, axis=1)
        cos_t = np.clip(np.sum(los * N0, axis=1) / r, 1e-3, 1.0)
        a0[:M][foot] = view.solid_angle[foot] * r[foot] ** 2 / cos_t[foot]
    # steady-state first bounce: q = rho / a = pi sum_k y_ii / phi
    y = view.capture.stir
    rows, cols = view.rows(), view.cols()
    q = np.full(M, np.nan)
    for r_, k in enumerate(rows):
        c = np.flatnonzero(cols == k)
        if c.size:
            q[k] = np.pi * max(float(np.sum(y[r_, c[0]])), 0.0)
    alb0 = np.full(M + Hn, 0.5)
    known_a = foot | given_area[:M]
    ok = np.isfinite(q) & (q > 0)
    g0 = 1.0 if view.radiometric else (float(geo.gain) if getattr(geo, "gain", None) else
                                       _gain_start(view, X, geo.pairs, q))
    alb0[:M][ok & known_a] = np.clip(q[ok & known_a] * a0[:M][ok & known_a] / g0, 0.05, 0.95)
    a0[:M][ok & ~known_a] = np.clip(0.5 * g0 / q[ok & ~known_a], 1e-6, 0.5)
    if geo.albedo is not None:
        sel = np.isfinite(geo.albedo)
        alb0[:M][sel] = np.clip(geo.albedo[sel], 0.01, 0.99)
    if geo.area is not None:
        sel = np.isfinite(geo.area) & ~known_a
        a0[:M][sel] = np.clip(geo.area[sel], 1e-6, 0.9)
    plane = flatland_plane(view, X) if pri.get("flatland") else None
    hp = [np.asarray(h.position, float) for h in hidden]
    hn = [np.asarray(h.normal, float) for h in hidden]
    if plane is not None:  # hidden starts into the plane (positions and normals)
        hp = [p_ - ((p_ - view.source) @ plane) * plane for p_ in hp]
        hn = [n_ - (n_ @ plane) * plane for n_ in hn]
    Z = np.vstack([X] + [p_[None] for p_ in hp]) if Hn else X
    Nn = np.vstack([N0] + [n_[None] / np.linalg.norm(n_) for n_ in hn]) if Hn else N0
    for j, h in enumerate(hidden):
        a0[M + j] = h.area
    names = [f"V{int(i)}" for i in ids] + [f"H{j + 1}" for j in range(Hn)]
    gl = np.zeros(M + Hn, bool)
    if isinstance(brdf, str):
        gl[:M] = brdf == "phong"
    else:  # which visible patches are glossy (the rest Lambertian)
        gl[:M] = np.asarray(brdf, bool)
    brdfs = [Phong(alb0[k] * 0.8, 0.1, 10.0) if gl[k] else Lambertian(float(alb0[k])) for k in range(M + Hn)]
    K = max(bounces or 2, 3 if Hn else 2)
    from ..radiometry import facing_matrix

    vis_m = facing_matrix(Z, Nn)
    if geo.pairs is not None:  # visible to visible: the legs the onsets measured
        vis_m[:M, :M] = np.asarray(geo.pairs, bool) & ~np.eye(M, dtype=bool)
    model = TransientModel(Z, Nn, a0, view.grid, view.irf, rows, cols, brdfs, source=view.source,
                           camera=view.camera, legs_included=view.capture.legs_included, bounces=K,
                           names=names, visibility=vis_m, bounces_hidden=3)
    # ---- visible patches
    known_pos = np.isfinite(view.known_xyz).all(axis=1)
    ray = np.isfinite(view.rays).all(axis=1) & ~known_pos
    free3 = ~known_pos & ~ray
    pstd = np.asarray(geo.position_std[:M], float) if geo.position_std is not None else np.full((M, 3), np.nan)
    w = view.grid.bin_width
    if not fixed_visible:
        for k in np.flatnonzero(ray):
            s = float(np.nanmax(pstd[k])) if np.isfinite(pstd[k]).any() else w
            b = 5.0 * s + 2.0 * w
            model.set_unknown("position", [k], lower=-b, upper=b, scale=max(s, 1e-5),
                              basis=view.rays[k].reshape(3, 1))
        for k in np.flatnonzero(free3):
            s = float(np.nanmax(pstd[k])) if np.isfinite(pstd[k]).any() else w
            b = 5.0 * s + 2.0 * w
            model.set_unknown("position", [k], lower=-b, upper=b, scale=max(s, 1e-5))
    if foot.any():
        model.set_footprint(np.flatnonzero(foot), view.solid_angle[foot])
    free_area = ~foot & ~given_area[:M]
    tilt_v = np.flatnonzero(~given_n)
    if not fixed_visible:
        model.set_unknown("albedo", np.arange(M))
        if free_area.any():
            model.set_unknown("area", np.flatnonzero(free_area), lower=1e-7, upper=1.0,
                              scale=np.maximum(a0[:M][free_area], 1e-6))
        if gl[:M].any():
            g_ = np.flatnonzero(gl[:M])
            model.set_unknown("specular", g_).set_unknown("exponent", g_, upper=200.0)
        if len(tilt_v):
            model.set_unknown("tilt", tilt_v).set_unknown("tilt2", tilt_v)
    if not view.radiometric:  # counts, volts...: the pulse energy x detector gain is unknown
        model.set_unknown_gain(g0)
    # ---- hidden patches
    notes = []
    if pri.get("flatland") and plane is None:
        notes.append("flatland prior ignored: the source and the visible patches do not span one plane")
    hid = np.arange(M, M + Hn)
    if Hn:
        model.set_albedo_product(hid)
        for j, h in enumerate(hidden):
            model.params["albedo"].value[M + j] = float(np.clip(h.albedo_area, 1e-9, 0.089))
        # albedo x area of a hidden patch: at most (albedo 1) x (0.3 m)^2
        model.set_unknown("albedo", hid, upper=0.09, scale=1e-3)
        eps = settings.constraints.hidden_eps
        if plane is not None:
            basis = np.stack([perpendicular(plane), np.cross(plane, perpendicular(plane))], axis=1)
            model.set_unknown("position", hid, lower=-eps, upper=eps, scale=eps / 5, basis=basis)
            model.set_tilt_axes(hid, plane)
            model.set_unknown("tilt", hid, lower=-np.radians(60), upper=np.radians(60))
        else:  # the normal stays within 60 deg of facing the visible patches it was found by
            model.set_unknown("position", hid, lower=-eps, upper=eps, scale=eps / 5)
            model.set_unknown("tilt", hid, lower=-np.radians(60), upper=np.radians(60))
            model.set_unknown("tilt2", hid, lower=-np.radians(60), upper=np.radians(60))
        ext = hid if extended is True else (np.array([M + j for j in sorted(extended)], int)
                                             if isinstance(extended, (set, list, tuple)) else np.zeros(0, int))
        if len(ext):
            model.set_extended(ext, rings=1, per_ring=6)
            model.set_unknown("area", ext, lower=1e-6, upper=0.09, scale=1e-3)
    model.setup(symbolic=symbolic)
    given = {"position": np.concatenate([known_pos, np.zeros(Hn, bool)]),
             "normal": np.concatenate([given_n, np.zeros(Hn, bool)]),
             "area": given_area.copy()}
    flat = None
    lab = getattr(geo, "flat_labels", None)
    if lab is not None and not fixed_visible:  # flatness: each normal perpendicular to its group
        pairs_f = []
        for g_ in np.unique(lab[lab >= 0]):
            idx = np.flatnonzero(lab == g_)
            for k in idx:
                if given_n[k]:
                    continue
                d = np.linalg.norm(X[idx] - X[k], axis=1)
                for j in idx[np.argsort(d)[1:5]]:
                    pairs_f.append((k, j))
        flat = np.array(pairs_f, int).reshape(-1, 2) if pairs_f else None
    gauge = None
    if view.frame == "source-origin" and free3.any() and not fixed_visible:
        fp = model.params["position"].free
        G = gauge_generators(view, model.params["position"].value, model.normals, model.blocks,
                             model.x_scale, fp, model.tilt_free, model)
        if len(G):
            gauge = (G, model.x0.copy())
    vis = np.concatenate([np.ones(M, bool), np.zeros(Hn, bool)])
    return ModelPlan(model, names, ids, vis, given, gauge, notes, flat)
