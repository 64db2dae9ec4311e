"""estimate.json (schema v2, docs/estimate-json.md) for a relay-wall reconstruction.

Every surface node (method "surface") or depth-map column inside the volume's mask (volumetric
methods) becomes a hidden patch: position, normal, area, albedo and their std. A volumetric map
has no error bars: its std are null with the reason in ``notes``. The ``surface`` object holds
the grid, the maps and the names of the files ``write_outputs`` writes.
"""
from __future__ import annotations

import math

import numpy as np

from .surface.mask import EDGE_ALBEDO_FLOOR, EDGE_ALBEDO_FLOOR_PRIOR, EDGE_DEPTH_FLOOR

__all__ = ["json_dict"]

UNITS = {"length": "m", "time": "m of optical path", "area": "m^2", "angle": "rad"}


def _l(a):
    return None if a is None else np.asarray(a, float).round(9).tolist()


def _pc(fraction: float) -> str:
    """A fraction as a percentage for the patches' notes, e.g. 0.05 -> "5 %"."""
    return f"{100 * fraction:g} %"


def _f(x):
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _surface_patches(est):
    s = est.surface
    P = s.points().reshape(-1, 3)
    Ps = s.position_std().reshape(-1, 3)
    nrm, nstd = s.normals.reshape(-1, 3), s.normal_std.reshape(-1, 3)
    _, _, area = s.grid.geometry(s.depth.ravel())
    rho, rstd = s.albedo.ravel(), s.albedo_std.ravel()
    mask = s.mask.ravel()
    edge = s.edge.ravel()
    rel = "relative albedo: the relay's absolute gain is unknown (scaled by one global factor)"
    out = []
    for k in range(len(P)):
        pid = est.id_base + k
        notes = {"area": "the grid cell's surface area (given by the grid, not estimated)"}
        if s.albedo_relative:
            notes["albedo"] = rel
        if not mask[k]:
            notes["mask"] = "outside the surface mask: the data do not see a surface here"
        if edge[k]:
            notes["edge"] = "at the surface's edge (a cell the edge may cut, or its neighbour): " + (
                f"the std are widened for the error of the edge's model (floors in quadrature: {_pc(EDGE_DEPTH_FLOOR)} "
                f"of the cell pitch in depth; in albedo the larger of {_pc(EDGE_ALBEDO_FLOOR)} of the bright albedo, "
                f"{_pc(EDGE_ALBEDO_FLOOR_PRIOR)} under the albedo prior with the posterior's std, and the node's "
                "departure from its mask neighbours' mean; mask.edge_std)"
                if s.edge_widened else
                "the std hold the noise only, not the error of modelling a partly covered cell as uniform")
        out.append({"id": pid, "name": f"H{pid}", "visible": False,
                    "position": _l(P[k]), "position_std": _l(Ps[k]),
                    "normal": _l(nrm[k]), "normal_std": _l(nstd[k]),
                    "area": _f(area[k]), "area_std": 0.0,
                    "albedo": _f(rho[k]), "albedo_std": _f(rstd[k]),
                    "albedo_area": _f(rho[k] * area[k]), "albedo_area_std": _f(rstd[k] * area[k]),
                    "in_mask": bool(mask[k]), "unidentifiable": [], "notes": notes})
    return out


def _map_patches(est):
    m = est.maps
    P = m.points().reshape(-1, 3)
    alb = m.albedo.ravel()
    out = []
    why = (f"{est.volume.method} volume: a volumetric reconstruction gives no error bars "
           "(use method='surface')")
    for k in np.flatnonzero(m.mask.ravel()):
        pid = est.id_base + int(k)
        out.append({"id": pid, "name": f"H{pid}", "visible": False, "position": _l(P[k]),
                    "position_std": None, "normal": None, "normal_std": None,
                    "albedo": _f(alb[k]), "albedo_std": None, "in_mask": True,
                    "unidentifiable": ["position_std", "normal", "normal_std", "albedo_std"],
                    "notes": {"position_std": why, "albedo_std": why,
                              "normal": "a depth map column has no fitted normal",
                              "albedo": "relative intensity of the volume (brightest column = 1)"}})
    return out


def json_dict(est) -> dict:
    """The estimate.json structure (schema v2) of an ``NLOSEstimate``."""
    s = est.surface
    checks = []
    if s is not None:
        # the result is the last level's solve; coarser levels only start it (their status is
        # listed, and a coarse level cut by its iteration limit is a note, not a failure)
        # a last level cut by its iteration limit passes when its remaining Gauss-Newton step
        # moves no mask node by CONVERGED_STD of its std (fit.py, _finish)
        from .surface.fit import CONVERGED_STD
        rem = s.extras.get("remaining_step")
        worst = None if rem is None else rem.get("max_std_mask")
        solved = bool(s.levels[-1]["success"]) if s.levels else False
        checks.append({"name": "solver", "passed": solved or bool(rem and rem.get("converged")),
                       "value": worst, "limit": None if rem is None else CONVERGED_STD,
                       "message": "; ".join(f"level {i}{' (coarse: starts the next)' if i < len(s.levels) - 1 else ''}: "
                                            f"{l['status']}" for i, l in enumerate(s.levels))
                       + ("" if worst is None else f"; the remaining Gauss-Newton step moves a mask node's depth or "
                          f"albedo by at most {worst:.3g} std (limit {CONVERGED_STD:g})")})
        lim = 1 + 5 * math.sqrt(2.0 / max(s.dof, 1))
        checks.append({"name": "chi2", "passed": s.chi2_dof <= lim, "value": s.chi2_dof, "limit": lim,
                       "message": f"whitened chi2/dof of the surface fit over {s.dof} dof"
                       + ("" if s.chi2_dof <= 1 else "; std inflated by sqrt(chi2/dof)")})
        det = s.extras.get("detection")
        if det:
            checks.append({"name": "detection", "passed": bool(det["detected"]), "value": det["chi2_gain"],
                           "limit": det["threshold"],
                           "message": f"the surface lowers the whitened chi2 by {det['chi2_gain']:.4g} against "
                           f"{det['threshold']:.4g} from noise alone (p = {det['p']:g})"})
        ex = s.extras.get("explained")
        if ex and "max_residual" in ex:
            checks.append({"name": "explained-returns", "passed": bool(ex["passed"]), "value": ex["max_residual"],
                           "limit": ex["threshold"],
                           "message": f"largest matched-filter chi2 of the whitened residual over "
                           f"[{ex['window'][0]:.4g}, {ex['window'][1]:.4g}] m of path: {ex['max_residual']:.4g} at "
                           f"{[round(a, 3) for a in ex['at']]} m, {ex['candidates']} candidate points, limit "
                           f"{ex['threshold']:.4g} (p = {ex['p']:g}); the data's own largest {ex['max_data']:.4g}"})
    patches = _surface_patches(est) if s is not None else _map_patches(est)
    c, u, v, w = est.relay.frame
    surf = {"method": est.method, "frame": {"centre": _l(c), "u": _l(u), "v": _l(v), "w": _l(w)},
            "volume": {"method": est.volume.method, "x": _l(est.volume.x), "y": _l(est.volume.y),
                       "z": [float(est.volume.z[0]), float(est.volume.z[-1]), int(len(est.volume.z))],
                       "info": {k: v for k, v in est.volume.info.items() if isinstance(v, (int, float, str, bool))}},
            "files": dict(est.files)}
    if s is not None:
        surf.update({"grid": {"x": _l(s.grid.x), "y": _l(s.grid.y)},
                     "maps": {"depth": _l(s.depth), "depth_std": _l(s.depth_std), "albedo": _l(s.albedo),
                              "albedo_std": _l(s.albedo_std), "mask": s.mask.astype(int).tolist(),
                              "edge": s.edge.astype(int).tolist()},
                     "edge_std_widened": bool(s.edge_widened),
                     "irf_fwhm": s.fwhm_irf, "irf_sigma": s.sigma_irf, "irf_sigma_std": _f(s.sigma_irf_std),
                     "response": s.response, "irf_tail": _f(s.tail), "irf_tail_std": _f(s.tail_std),
                     "brdf": s.brdf,
                     "background": s.background, "gain": s.gain, "albedo_relative": s.albedo_relative,
                     "prior_weight": s.prior_weight, "prior_method": s.prior_method,
                     "std_basis": s.extras.get("std_basis", "fisher"),
                     "chi2_dof": s.chi2_dof, "dof": s.dof, "levels": s.levels})
    else:
        surf.update({"grid": {"x": _l(est.maps.x), "y": _l(est.maps.y)},
                     "maps": {"depth": _l(est.maps.depth), "albedo": _l(est.maps.albedo),
                              "mask": est.maps.mask.astype(int).tolist()}})
    sig = None if s is None else (est.relay.sigma if isinstance(est.relay.sigma, float) else None)
    return {"format": "stircasadi.estimate", "version": 2, "units": UNITS,
            "success": est.success, "verdict": "OK" if est.success else "UNRELIABLE",
            "reasons": list(est.reasons), "frame": "capture",
            "source_xyz": _l(est.source_xyz), "camera_xyz": _l(est.camera_xyz),
            "patches": patches, "covariance": None,
            "distances": {"ids": [], "matrix": [], "eps": [], "eps_level": 0.99},
            "noise": {"sigma": sig, "source": None if s is None else s.extras.get("noise"),
                      "capture_sigma": est.relay.sigma if isinstance(est.relay.sigma, float) else None},
            "checks": checks, "ambiguities": [], "priors": {} if s is None else
            {"smoothness": {"weight": s.prior_weight, "method": s.prior_method,
                            "albedo_relative_weight": s.extras.get("albedo_prior", 0.0)}},
            "stages": est.stages, "surface": surf}
