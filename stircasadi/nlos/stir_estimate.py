"""``stircasadi estimate --method surface`` on a full STIR: the joint visible fit, then the hidden
surface behind its visible patches from their third bounce (Fig. 13).

When to use: a full STIR with its source and camera legs whose hidden part is one surface seen
only through third bounces (``problems/three_planes_occluded``). The library route without the
joint fit (visible patches known) is :func:`stircasadi.nlos.stir_surface.hidden_surface_from_stir`.

Steps of :func:`add_stir_surface`
---------------------------------
1. The visible patches come from the joint fit (``pipeline.estimate_capture`` with no hidden
   patch): its positions, normals, Lambertian albedos and areas (the fitted values also where
   the joint fit reports one unidentified: the subtraction needs a number; the reason stays in
   that patch's notes). Occluders are unknown to the estimator (the capture holds none outside
   ``truth/``): the visible patches' own STIR is simulated without them.
2. ``hidden_surface_from_stir`` with every ``ill_step``-th illumination, ``ill_step`` chosen so
   that at most ``max_traces`` traces remain (the fit's cost grows with traces x nodes).
3. The estimate: the joint fit's estimate.json with every surface node appended as a hidden
   patch (``nlos.report``), the ``surface`` object (grid, maps, response, prior, levels), the
   surface fit's checks (solver, chi2) prefixed ``surface-``, and ``success`` only when both the
   visible fit and the surface fit pass. A visible fit that fails leaves second-bounce residuals
   the surface cannot explain; the surface is still fitted and reported, flagged.

Status (measured 2026-12-02, ``stircasadi simulate three_planes_occluded`` at the problem's own
1e-6 noise, then ``stircasadi estimate f13.h5 --method surface``; 2-core VM, a second heavy
process on the other core part of the time): exit 3, UNRELIABLE. 1044 s in all (the joint fit
of the 98 visible patches, chi2/dof 1.0, flagged by its linearity check; the surface 820 s, of
which the final 8 x 8 fit 605 s, 980 traces at ill_step 10), max RSS 3.6 GB. The surface fit
stops at its iteration limit (flagged) with chi2/dof 1.00 and 1 of 64 nodes in its mask, and
that node lies 1.1 m from the panel (std 7 cm): at 1e-6 the panel's third bounce is ~1 noise std
per bin and the route does not find it (``stir_surface``'s status). At 1e-8 the joint fit
models the visible third bounce (77 noise std): it ran over 30 min and reached 17 GB resident
before it was stopped, so the route is not yet usable there on this machine.

Neglects: what ``stir_surface`` neglects, and the occluders' shadows of visible paths (step 1).
"""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from ..errors import ReconstructionError
from .estimate import NLOSEstimate
from .stir_surface import VisiblePatches, hidden_surface_from_stir

__all__ = ["add_stir_surface", "visible_from_joint", "SUPERSEDED"]

#: joint-fit checks of the residual that the hidden surface's light fails by design
SUPERSEDED = ("chi2", "trace-residuals", "unexplained-returns")


def visible_from_joint(result) -> VisiblePatches:
    """The visible patches of a joint ``pipeline.EstimateResult`` (fitted values, see step 1)."""
    est, view = result.fit.estimate, result.view
    M = len(view.ids)
    vals = {q: np.asarray(est.values[q], float)[:M] for q in ("position", "normal", "albedo", "area")}
    bad = [q for q, v in vals.items() if not np.isfinite(v).all()]
    if bad or (vals["area"] <= 0).any() or (vals["albedo"] < 0).any():
        raise ReconstructionError(f"The joint fit's visible patches have non-finite or non-physical {bad or 'area/albedo'} "
                                  "values; the hidden surface needs them to remove the visible light. "
                                  "Check the joint fit (estimate without --method) first.")
    n = vals["normal"] / np.linalg.norm(vals["normal"], axis=1, keepdims=True)
    return VisiblePatches(np.asarray(view.ids), vals["position"], n, vals["albedo"], vals["area"], None)


def add_stir_surface(result, capture, out_dir=None, max_traces: int = 1000, settings=None,
                     time_left: float | None = None):
    """Append the hidden surface to the joint ``result`` (``pipeline.EstimateResult``) of a full
    STIR ``capture``; write its maps, mesh and pictures to ``out_dir`` (see the module docstring).
    ``time_left``: seconds of the estimate's time limit left (None: no limit); at or below 0 the
    surface is skipped and the estimate flagged."""
    from ..report import jsonable

    d = dict(result.json)
    stages = dict(d.get("stages", {}))
    if time_left is not None and time_left <= 0:
        stages["surface"] = {"status": "skipped: the time limit ran out in the joint fit", "success": False}
        reasons = list(d.get("reasons", [])) + ["surface: skipped, the time limit ran out in the joint fit"]
        d.update(stages=stages, reasons=reasons, success=False, verdict="UNRELIABLE")
        result.json = jsonable(d)
        return result
    vis = visible_from_joint(result)
    n_ill, n_obs = capture.stir.shape[:2]
    step = max(1, math.ceil(n_ill * n_obs / max(int(max_traces), 1)))
    t0 = time.perf_counter()
    # the joint fit's frame (source at the origin unless the capture fixes it): source and
    # camera as the fit placed them, so that the surface lies in the visible patches' frame
    cap = replace(capture, source_xyz=np.asarray(result.view.source, float),
                  camera_xyz=np.asarray(result.view.camera, float))
    r = hidden_surface_from_stir(cap, vis, settings, ill_step=step)
    s = r.surface
    base = max(int(p["id"]) for p in d["patches"]) + 1 if d.get("patches") else 0
    surf_stage = {"status": "; ".join(l["status"] for l in s.levels), "success": s.success,
                  "iterations": int(sum(x["iterations"] for l in s.levels for x in l["solves"])),
                  "wall_time_s": time.perf_counter() - t0, "ill_step": step, **s.summary(),
                  "stats": {k: v for k, v in r.stats.items() if isinstance(v, (int, float, str, bool))}}
    nest = NLOSEstimate("surface", r.relay, r.volume, r.maps, s, stages={"surface": surf_stage},
                        reasons=list(s.reasons), id_base=base, source_xyz=cap.source_xyz,
                        camera_xyz=cap.camera_xyz)
    if out_dir is not None:
        nest.write_outputs(out_dir)
    nd = nest.to_json_dict()
    # the joint fit's residual checks see the hidden light the surface is fitted to: where they
    # fail, the surface fit's chi2 over the third-bounce traces (visible light subtracted) judges
    # instead; they stay listed, marked superseded
    joint_checks, joint_reasons = [], []
    for c in d.get("checks", []):
        c = dict(c)
        if c["name"] in SUPERSEDED and not c["passed"]:
            c["superseded_by"] = "surface-chi2"
            c["message"] += (" [superseded: the hidden light is what the surface fit explains; its "
                             "chi2 over the third-bounce traces judges the residual]")
        elif not c["passed"]:
            joint_reasons.append(f"{c['name']}: {c['message']}")
        joint_checks.append(c)
    checks = joint_checks + [dict(c, name=f"surface-{c['name']}") for c in nd["checks"]]
    # the surface's reasons already name a failed solve and a chi2 above its check's limit
    reasons = joint_reasons + [f"surface: {x}" for x in s.reasons]
    ok = bool(result.fit.estimate.success) and not joint_reasons and s.success
    stages["surface"] = surf_stage
    priors = dict(d.get("priors", {}))
    priors.update(nd.get("priors", {}))
    d.update(patches=list(d["patches"]) + nd["patches"], checks=checks, reasons=reasons, success=ok,
             verdict="OK" if ok else "UNRELIABLE", stages=stages, surface=nd["surface"], priors=priors)
    result.json = jsonable(d)
    result.extra["stir_surface"] = r
    return result
