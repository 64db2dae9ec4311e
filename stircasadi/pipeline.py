"""The inverse route, top to bottom: ``Capture -> CaptureView -> GeometryEstimate -> joint fit ->
checks -> estimate.json``.

``estimate_capture(capture, ...)`` is what ``stircasadi estimate`` and ``stircasadi run`` call,
and what studies, applications and user scripts should call. It never reads the capture's
``truth``. Its ``EstimateResult.to_json_dict()`` is the structure of docs/estimate-json.md; its
``success`` is true only when every solve converged and every self-check passed.

Route: full STIRs with the source and camera legs go through onsets -> distances -> positions
(``stircasadi.geometry``) and the joint CasADi/IPOPT fit of everything the data identify, with
hidden patches found in the residual (``stircasadi.joint``); paired or rectified relay-wall scans
go to the relay-wall reconstruction (``stircasadi.geometry.relay``).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from . import __version__
from .errors import GeometryError, ModelError
from .progress import get_logger
from .view import CaptureView

__all__ = ["estimate_capture", "EstimateResult"]

log = get_logger(__name__)
UNITS = {"length": "m", "time": "m of optical path", "area": "m^2", "angle": "rad"}


@dataclass
class EstimateResult:
    """What the inverse route returns: the JSON structure and the objects behind it."""

    json: dict
    geometry: object = None
    fit: object = None
    view: object = None
    extra: dict = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return bool(self.json.get("success", False))

    def to_json_dict(self) -> dict:
        return self.json


def _priors(areas, flatland) -> dict:
    out = {}
    if areas is not None:
        if isinstance(areas, dict):
            out["areas"] = {int(k): float(v) for k, v in areas.items()}
        else:
            raise ModelError(f"areas must be a dict {{patch id: m^2}}; got {type(areas).__name__}.")
        bad = {k: v for k, v in out["areas"].items() if not (v > 0 and np.isfinite(v))}
        if bad:
            raise ModelError(f"declared areas must be > 0 m^2; got {bad}.")
    if flatland is not None:
        out["flatland"] = bool(flatland)
    return out


def estimate_capture(capture, hidden: int | None = None, brdf: str = "lambertian", areas=None,
                     flatland: bool | None = None, settings=None, method: str | None = None,
                     out_dir=None, time_limit: float | None = None,
                     nlos_options: dict | None = None) -> EstimateResult:
    """Estimate geometry, reflectance and hidden patches from ``capture`` (see module docstring).

    hidden : number of hidden patches to place (None: as many as the data ask for).
    brdf : ``"lambertian"`` or ``"phong"`` (a Phong lobe on every visible patch).
    areas : declared patch areas {id: m^2} (priors; the capture's ``priors/`` group may hold them).
    flatland : every patch lies in the plane of the source and the visible patches (prior).
    method : relay-wall scans only: ``"relay"`` (default: the first hidden point and plane from
        onsets), or ``"lct"``, ``"fk"``, ``"bp"``, ``"surface"`` (``stircasadi.nlos``: volumes and
        a fitted hidden surface, written to ``out_dir`` with their maps, mesh and pictures).
        A full STIR with legs: ``None`` / ``"joint"`` (the joint fit), or ``"surface"`` (the joint
        fit of the visible patches, then the hidden surface from their third bounce:
        ``nlos.stir_estimate``; the surface fit itself is not stopped by ``time_limit``, it is
        skipped when the joint fit used the limit up).
    time_limit : wall-clock seconds for the whole estimate (overrides ``settings.time_limit``):
        where it runs out the stages left are skipped and the result is the last converged fit,
        flagged UNRELIABLE by the ``time-limit`` check (``stircasadi.joint.budget``).
    nlos_options : relay-wall scans with ``method`` "lct", "fk", "bp" or "surface" only: options of
        ``stircasadi.nlos.estimate_capture`` (``VolumeSettings`` / ``SurfaceSettings`` fields,
        ``init``, ``wall_step``, ``gain``); an unknown one is refused with the known ones.
    """
    from .joint.settings import EstimateSettings

    if brdf not in ("lambertian", "phong"):
        raise ModelError(f"brdf must be 'lambertian' or 'phong'; got {brdf!r}.")
    if hidden is not None and (not isinstance(hidden, (int, np.integer)) or hidden < 0):
        raise ModelError(f"hidden must be None or an integer >= 0; got {hidden!r}.")
    settings = settings or EstimateSettings()
    if time_limit is not None:
        import copy

        settings = copy.copy(settings)
        settings.time_limit = time_limit
    settings = settings.validate()
    t0 = time.perf_counter()
    view = CaptureView.of(capture, _priors(areas, flatland))
    if nlos_options:
        from .nlos.estimate import METHODS as NLOS_METHODS
        if method not in NLOS_METHODS:
            raise ModelError(f"nlos_options are for method {' / '.join(map(repr, NLOS_METHODS))} on a "
                             f"relay-wall scan; got method={method!r}.")
    if capture.stir is None or not capture.legs_included:
        return _relay(capture, view, t0, method, out_dir, nlos_options)
    if nlos_options:
        raise ModelError("nlos_options are for relay-wall scans (paired or rectified traces); a full STIR "
                         "with its legs takes method='surface' with the route's own settings "
                         "(library: stircasadi.nlos.stir_surface.hidden_surface_from_stir).")
    if method not in (None, "joint", "surface"):
        raise ModelError(f"method={method!r} is for relay-wall scans (paired or rectified traces); "
                         "a full STIR with its legs is estimated by the joint fit (method=None or "
                         "'joint'), or by the joint fit of its visible patches followed by the hidden "
                         "surface behind them from their third bounce (method='surface', Fig. 13; "
                         "library: stircasadi.nlos.stir_surface.hidden_surface_from_stir).")
    if method == "surface":
        if hidden not in (None, 0):
            raise ModelError(f"method='surface' fits the hidden part as one surface; hidden={hidden} hidden "
                             "patches cannot be placed as well. Leave hidden unset (or 0), or use "
                             "method='joint' to place hidden point patches.")
        hidden = 0
    from .geometry import estimate_geometry
    from .joint.checks import identifiability_check, run_checks
    from .joint.budget import Budget
    from .joint.fit import fit_joint
    from .joint.policy import VisibleStart
    from .joint.result import patch_records

    geo = estimate_geometry(capture, hidden=0 if hidden == 0 else None)
    t_geo = time.perf_counter() - t0
    M = len(view.ids)
    if not np.array_equal(np.asarray(geo.ids[:M]), view.ids):
        raise GeometryError("internal: geometry ids differ from the capture's visible ids")
    from .geometry.normals import flat_groups, initial_normals

    X = np.asarray(geo.positions[:M])
    pairs = _second_bounce_pairs(view, geo, X)
    ps = np.asarray(geo.position_std[:M], float)
    e = geo.eps[:M, :M][np.isfinite(geo.eps[:M, :M]) & (geo.eps[:M, :M] > 0)]
    sig = float(np.nanmedian(ps)) if np.isfinite(ps).any() else (
        float(np.median(e)) / 2.576 if e.size else view.grid.bin_width)
    labels, gn, gstd = flat_groups(X, pairs, sig)
    cam = geo.camera_xyz if geo.camera_xyz is not None else view.camera
    n0, _ = initial_normals(X, pairs, cam, labels=labels)
    start = VisibleStart(X, ps, n0, pairs=pairs, flat_labels=labels)
    t1 = time.perf_counter()
    fit = fit_joint(view, start, settings, n_hidden=hidden, brdf=brdf,
                    budget=Budget(settings.time_limit, start=t0))
    t_fit = time.perf_counter() - t1
    first = geo.onsets.get("r")
    first = None if first is None else 2.0 * np.asarray(first) if view.colocated else None
    checks = run_checks(view, fit, settings, first_paths=first)
    est = fit.estimate
    n_h = est.values["position"].shape[0] - M
    checks.append(identifiability_check(view, geo.ambiguities, est.values["position"][:M], n_h))
    base = int(max(view.ids.max(), view.ill.max(), view.obs.max())) + 1
    ids = np.concatenate([view.ids, base + np.arange(n_h)])
    vis = np.concatenate([np.ones(M, bool), np.zeros(n_h, bool)])
    names = [f"V{int(i)}" for i in view.ids] + [f"H{int(i)}" for i in ids[M:]]
    patches = patch_records(est, ids, vis, names, brdf)
    failed = [c for c in checks if not c.passed]
    reasons = [f"{c.name}: {c.message}" for c in failed]
    success = est.success and not failed
    amb = [a for a in geo.ambiguities if a.get("kind") not in ("hidden-normals-unmeasured",
                                                              "unexplained-hidden-returns")]
    cov = _covariance(est, patches, ids, fit.plan.names)
    out = {
        "format": "stircasadi.estimate", "version": 2, "producer": f"stircasadi {__version__}",
        "units": UNITS, "success": bool(success), "verdict": "OK" if success else "UNRELIABLE",
        "reasons": reasons, "frame": view.frame,
        "source_xyz": view.source, "camera_xyz": view.camera,
        "patches": patches, "covariance": cov,
        "distances": {"ids": geo.ids[:M], "matrix": geo.distances[:M, :M], "eps": geo.eps[:M, :M],
                      "eps_level": geo.eps_level},
        "noise": {"sigma": fit.sigma, "source": fit.sigma_source, "capture_sigma": view.capture_sigma},
        "chi2_dof": est.chi2_dof, "checks": [c.to_dict() for c in checks],
        "ambiguities": amb + [{"kind": "note", "patch_ids": [], "message": n} for n in fit.notes],
        "priors": view.priors,
        "irf": {"kind": getattr(view.irf, "kind", "ideal"), "fwhm_m": getattr(view.irf, "fwhm", None),
                "source": view.irf_source},
        "stages": {**{k: (v.to_dict() if hasattr(v, "to_dict") else v) for k, v in geo.stats.items()},
                   "joint": {"status": est.status, "success": est.success, "solver": est.solver,
                             "iterations": est.iterations, "wall_time_s": t_fit,
                             "chi2_dof": est.chi2_dof, "std_inflation": est.inflation,
                             "flags": est.flags, "search": fit.history, **est.extra.get("model", {})},
                   "geometry_total": {"wall_time_s": t_geo},
                   "time_limit": fit.budget.to_dict() if fit.budget is not None else None},
    }
    from .report import jsonable

    res = EstimateResult(jsonable(out), geometry=geo, fit=fit, view=view)
    if method == "surface":
        from .nlos.stir_estimate import add_stir_surface

        left = None if not settings.time_limit else settings.time_limit - (time.perf_counter() - t0)
        res = add_stir_surface(res, capture, out_dir=out_dir, time_left=left)
    return res


def _second_bounce_pairs(view, geo, X) -> np.ndarray:
    """(M, M) bool: the pairs whose second bounce the data show — a measured distance that agrees
    with the placed positions within 5 std plus a bin (a later family detected in its place, a
    path through a third patch, is longer), and, where a calibrated camera gives the normals,
    that face each other."""
    from .radiometry import facing_matrix

    M = len(X)
    D = np.asarray(geo.distances[:M, :M], float)
    sd = np.asarray(geo.eps[:M, :M], float) / 2.576
    geo_d = np.linalg.norm(X[:, None] - X[None], axis=2)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(D) & (np.abs(D - geo_d) <= 5.0 * np.where(np.isfinite(sd), sd, 0.0)
                               + view.grid.bin_width)
    np.fill_diagonal(ok, False)
    n = view.known_normals
    if np.isfinite(n).all():
        ok &= facing_matrix(X, n)
    return ok & ok.T


def _covariance(est, patches, ids, plan_names):
    """The joint covariance of the reported (non-null) numbers, named ``quantity[id].x``."""
    keep, names = [], []
    idx = {n: k for k, n in enumerate(est.q_names)}
    for k, p in enumerate(patches):
        for q in ("position", "normal", "area", "albedo", "albedo_area", "specular", "exponent"):
            if p.get(q) is None or q not in est.values or (p.get("notes", {}).get(q) == "given"):
                continue
            width = 3 if q in ("position", "normal") else 1
            for c in range(width):
                key = f"{q}[{plan_names[k]}]" + ("" if width == 1 else f".{'xyz'[c]}")
                if key in idx:
                    keep.append(idx[key])
                    names.append(f"{q}[{int(ids[k])}]" + ("" if width == 1 else f".{'xyz'[c]}"))
    C = est.cov_q[np.ix_(keep, keep)] if keep else np.zeros((0, 0))
    return {"parameters": names, "matrix": C}


def _relay(capture, view, t0, method=None, out_dir=None, nlos_options=None) -> EstimateResult:
    from .geometry.relay import estimate_relay
    from .report import jsonable

    if method not in (None, "relay"):
        from .nlos import estimate_capture as nlos_estimate

        est = nlos_estimate(capture, method=method, out_dir=out_dir, **(nlos_options or {}))
        d = est.to_json_dict()
        d.setdefault("priors", view.priors)
        return EstimateResult(jsonable(d), geometry=est, view=view)
    geo = estimate_relay(capture)
    d = geo.to_json_dict()
    d.update({"version": 2, "units": UNITS, "verdict": "OK" if geo.success else "UNRELIABLE",
              "reasons": [] if geo.success else ["relay-wall stage failed"], "checks": [],
              "priors": view.priors, "covariance": None})
    d.setdefault("stages", {})["joint"] = {
        "status": "skipped: paired or rectified relay-wall traces go to the relay-wall "
                  "reconstruction (no joint STIR fit)", "success": None}
    d["stages"]["total"] = {"wall_time_s": time.perf_counter() - t0}
    return EstimateResult(jsonable(d), geometry=geo, view=view)

