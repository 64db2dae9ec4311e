"""Cells the hidden surface's edge cuts: step 4c of ``fit.py``.

When to use: called by ``fit_surface`` after its last level's solve
(``SurfaceSettings.edge_offsets``); nothing else needs it.

The model spreads each cell's albedo uniformly about its node, but a cell the surface's edge
cuts emits from its covered part only, off-centre. On a tilted surface that moves its return in
time, and the fit answers with depths that alternate row by row over the whole surface (central
differences leave the even and odd nodes free of each other) and with the response's width.
So the nodes of ``mask.cut_cells`` (the support's border) get a free in-plane centroid each
(the covered part's first moment, bounded to the cell: ``SurfaceModel(offset_nodes=...)``), the
level is solved again from its solution, and the centroids are kept when the likelihood ratio of
the two nested models (2 K more unknowns) exceeds the chi^2 quantile of 2 K degrees of freedom
at p = ``CUT_P``, the statistic divided by the inflation max(1, chi2/dof) of the model with
the centroids (``lm.nested_lr``); else the uniform cells stand. Where step 4b's pruned solve
stopped once its model was kept (``prune_nodes(early=True)``), this solve starts from there and
the restricted model's F is estimated by the quadratic model at its start
(``restricted_optimum``), taken no higher than the F of the level's solve before pruning (a model
that nests the pruned one, so its optimum lies lower): centroids the ratio against that keeps are
kept, and where it does not keep them the pruned solve is settled and the test made again against
its F. The quadratic model's estimate alone is low where that model overpromises and high where
it underpromises: 0.0004 of the start's excess above the optimum on the test's 5 x 5 scene, but
16 % above a settled solve's F from a start at 1.5 x where the data hold centroids the model
lacks (the test's scene), which kept centroids that solve did not keep; the floor refuses that.

Extents (``SurfaceSettings.edge_extent``): a centroid is the covered part's first moment only;
the part is also narrower than the cell, so its delay spread is smaller. Where the centroids are
kept, the model with a shrink (s_u, s_v) in [0, 0.9] of each cut cell's emitting part's sides
about its centroid (``SurfaceModel(cell_extent=True)``; the area, and so the albedo's meaning,
stay the cell's) is linearised at the centroids' solution (shrinks zero), and the quadratic
model there estimates both optima (shrinks held: taken no higher than the centroids' solve's F,
which a solve cut by its iteration limit would otherwise credit to the shrinks; shrinks free).
Only where the estimated ratio passes the test (2 K more unknowns) is that model solved from
there, first for ``EXTENT_PROBE`` iterations: the quadratic model overpromises (486 against the
146 that a solve of 12 iterations reached on the 32 x 32 chart; the undamped step itself
overshoots), so the probe must pass the same test on its own F before the solve goes on, and
the shrinks are kept where it does. One linearisation, or a probe, where the data do not ask
for the shrinks, not a whole solve (the 32 x 32 chart's time: a solve of 12 iterations there
is about 40 s).
Measured on the coverage study's seeds 800-823 at 0.1 % noise (where the edge model's error
shows): 13 OK / 11 FLAGGED / 0 SILENT-WRONG and 83 of 92 claims within 2 std (0.902), against 8 /
15 / 1 and 65 of 76 (0.855) with centroids alone, the shrinks kept on 20 of the 24; at the study's
drawn noise 22 / 2 / 0 and 40 of 44 (21 / 3 / 0 and 40 of 44 before), kept on 4. A shrink tied to the centroid
(a part flush with a side, (1 - 2|o| / h) of the cell) was worse (5 / 18 / 1): on edges oblique
to the grid the covered part is a triangle or a pentagon, not such a strip.

Shear (``SurfaceSettings.edge_shear``, off by default): the emitting part a parallelogram, its
v side leaning by a free k in [-0.9, 0.9] beside the shrinks (``SurfaceModel(cell_shear=True)``,
3 K more unknowns in the shrinks' test), so its second moments are any 2 x 2 covariance, a
triangle's u-v covariance included. Measured at 0.1 % noise (``python
benchmarks/surface_coverage.py 12 800 --noise=0.001 --edge_shear=true``, and 812; 24 900 for
fresh seeds; each against the default in the same session): chi2/dof fell on 38 of 48 scenes
(seed 809 3.12 -> 1.36, 923 5.83 -> 1.96, 919 1.63 -> 1.19), seeds 800-823 14 OK / 9 FLAGGED
/ 1 SILENT-WRONG with OK claims 76 of 84 within 2 std (default: 13 / 11 / 0, 83 of 92), seeds
900-923 10 / 14 / 0 with 59 of 66 (default: 9 / 15 / 0, 57 of 64); at the drawn noise 22 / 2 / 0
and 40 of 44 either way. Not the default because of seed 819 (a spherical cap, paired relay),
OK with 2 of its 10 claimed numbers beyond 2 std and SILENT-WRONG with 3: its depths alternate
node by node along x by about +-100 um (2-3 std) in both models, a mode the normals' central
differences do not see, and the shear moves one albedo from 1.03 to 2.03 std. (A test of the
depth map's fourth differences against their covariance does not catch it: BENCHMARKS.md.)
"""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from .lm import _damping, _free, first_linearisation, nested_lr, prior_gradient, prior_penalty
from .mask import cut_cells

__all__ = ["CUT_P", "cell_offsets", "fit_cut_cells", "restricted_optimum"]

#: false-alarm probability of the likelihood-ratio test that keeps the cut cells' centroids:
#: the nested model with 2 K more unknowns must lower chi^2 by more than chance would
CUT_P = 0.01

#: iterations of the shrinks' probe solve (the module docstring): it must pass the test to go on
EXTENT_PROBE = 4


def restricted_optimum(model, bounds, lin: dict, state, lam: float, R, hold=None):
    """F = chi^2 / 2 + prior at the optimum of the model without the cut cells' centroids,
    estimated from ``model``'s linearisation ``lin`` at ``state`` (centroids zero: there the
    model is the one without them): F at ``state`` less half the decrease of 2F that the undamped
    Gauss-Newton step on the other free unknowns predicts (``lm._free``: the projected step LM
    makes; 2F is the whitened chi^2 plus the prior's penalty): low where the quadratic model
    overpromises, high where it underpromises. ``hold``: the packed unknowns held (at their value
    in ``state``, zero: the nested model's), default every cut cell's unknowns."""
    N, M = model.N, R.shape[0]
    H, g = np.array(lin["H"], float), prior_gradient(lin["g"], state, lam, R)
    f = 0.5 * float(lin["chi2"]) + prior_penalty(state, lam, R)
    if lam > 0:
        H[:M, :M] += lam * R
    lo, hi = bounds.lo.copy(), bounds.hi.copy()
    hold = np.arange(model.npar - model.E * model.K, model.npar) if hold is None else np.asarray(hold, int)
    lo[hold] = hi[hold] = 0.0          # held (the centroids, or the shrinks): not free
    b = SimpleNamespace(lo=lo, hi=hi)
    fi, d = _free(model, state, model.pack(state), H, g, b, _damping(np.diag(H), N, hi[N:2 * N] <= 0.0))
    return f - 0.5 * max(-float(g[fi] @ d), 0.0) if len(fi) else f


def fit_cut_cells(shape, state, res: dict, y, wgt, make_model, make_bounds, solve, settle=None,
                  quad: dict | None = None, extent: bool = False) -> dict | None:
    """The level solved again with its cut cells' centroids free (``extent``: and their emitting
    parts' shrinks, the module docstring), from ``state`` (the solution ``res`` of the level's own
    solve). ``make_model(nodes, extent=False)``: the level's model with those offset nodes;
    ``make_bounds(model)``; ``solve(model, bounds, state, lin0=None)``: the level's solver.

    ``settle``: given when ``res`` stopped short of its optimum (step 4b's pruned solve, stopped
    once its model was kept): a function that solves it on and returns that solve. The
    restricted model's F is then first taken from ``restricted_optimum`` on the new solve's first
    linearisation (``quad``: ``lam``, ``R``, ``dtype`` of the level's solver, and ``floor``: F of
    a solve of a model that nests the restricted one, the level's solve before pruning, whose
    optimum lies below the restricted one's: the estimate is taken no higher); only when the
    centroids fail the test against that is ``res`` settled and the test made again against its
    F.

    Returns None (no cell cut), or a dict: ``info`` (nodes, the likelihood ratio ``lr``, its
    ``threshold`` at ``p``, ``kept``, ``reference``: ``solve`` or ``estimate``, the F the
    ratio was taken against, the solve's ``status`` and ``iterations``; ``extent``: the shrinks'
    test, ``lr_estimate`` (the quadratic model's), ``threshold``, ``f_reference``, whether their
    model was ``probed`` and then ``lr_probe``, and its solve's ``lr``, ``status`` and
    ``iterations``, and ``kept``), that
    solve's ``model``, ``bounds`` and ``res``, and ``restricted``: the settled solve (None unless
    made)."""
    band = cut_cells(np.asarray(state.rho).reshape(shape))
    if not band.size:
        return None
    model = make_model(band)
    bounds = make_bounds(model)
    s0 = replace(state, off=np.zeros((band.size, 2)))
    lin0, f_ref, ref, settled = None, float(res["f"]), "solve", None
    q = quad or {"lam": 0.0, "R": np.zeros((model.N, model.N)), "dtype": np.float64}

    def ratio(f_restricted, f, chi2, m, per=2):      # the test of ``per`` K more unknowns of ``m``: (lr, threshold)
        return nested_lr(f_restricted, f, chi2, int(np.size(y)) - m.npar, per * band.size, CUT_P)

    def chi2_of(m, out):
        return float(m.objective(out["state"], y, wgt)[0])

    if settle is not None:
        s0, lin0 = first_linearisation(model, bounds, s0, y, wgt, q["dtype"])
        f_ref = restricted_optimum(model, bounds, lin0, s0, q["lam"], q["R"])
        f_ref, ref = min(f_ref, float(q.get("floor", np.inf))), "estimate"
    out = solve(model, bounds, s0, lin0=lin0)
    chi2 = chi2_of(model, out)
    lr, need = ratio(f_ref, out["f"], chi2, model)
    if settle is not None and lr <= need:
        settled = settle()
        f_ref, ref = float(settled["f"]), "solve"
        lr, need = ratio(f_ref, out["f"], chi2, model)
    info = {"nodes": int(band.size), "lr": lr, "threshold": need, "p": CUT_P, "kept": bool(lr > need),
            "reference": ref, "f_reference": f_ref, "status": out["status"], "iterations": out["iterations"]}
    if extent and info["kept"]:
        # the shrinks too? The model with them linearised at this solution (shrinks zero): the
        # quadratic model's optimum with the shrinks held (taken no higher than this solve's F: a
        # solve cut by its iteration limit would credit its unfinished descent to them) and with
        # them free; only where the estimated ratio passes is that model probed (then solved on),
        # and kept by the same test on its own F
        m2 = make_model(band, extent=True)
        b2 = make_bounds(m2)
        s1, lin1 = first_linearisation(m2, b2, out["state"], y, wgt, q["dtype"])
        per = m2.E - 2             # the shrinks [and shear] per cut cell
        shrinks = np.arange(m2.npar - m2.E * band.size, m2.npar).reshape(band.size, m2.E)[:, 2:].ravel()
        f1 = min(float(out["f"]), restricted_optimum(m2, b2, lin1, s1, q["lam"], q["R"], hold=shrinks))
        f_est = restricted_optimum(m2, b2, lin1, s1, q["lam"], q["R"], hold=[])
        lr_est, need2 = ratio(f1, f_est, float(lin1["chi2"]), m2, per)
        ext = info["extent"] = {"lr_estimate": lr_est, "threshold": need2, "f_reference": f1, "probed": False,
                                "kept": False}
        if lr_est > need2:
            # the quadratic model overpromises (486 against the 146 a solve reached on the 32 x 32
            # chart): a probe of EXTENT_PROBE iterations must pass the test before the solve goes on
            out2 = solve(m2, b2, s1, lin0=lin1, max_iter=EXTENT_PROBE)
            lr2, _ = ratio(f1, out2["f"], chi2_of(m2, out2), m2, per)
            ext.update({"probed": True, "lr_probe": lr2, "lr": lr2, "kept": bool(lr2 > need2),
                        "status": out2["status"], "iterations": out2["iterations"]})
            if lr2 > need2 and out2["status"].startswith("Maximum"):
                more = solve(m2, b2, out2["state"])          # kept: solved on (F only falls)
                lr2, _ = ratio(f1, more["f"], chi2_of(m2, more), m2, per)
                ext.update({"lr": lr2, "status": more["status"], "iterations": out2["iterations"] + more["iterations"]})
                out2 = more
            if lr2 > need2:
                model, bounds, out = m2, b2, out2
    return {"info": info, "model": model, "bounds": bounds, "res": out, "restricted": settled}


def cell_offsets(model, state) -> dict | None:
    """The result's record of step 4c (``extras["cell_offsets"]``): the cut cells' ``nodes``,
    their centroid offsets ``offset_m`` (K, 2) and, with extents, their ``shrink`` (K, 2); None
    without cut cells."""
    if not model.K:
        return None
    off = model.centroid_offsets(state)
    return {"nodes": model.onodes.tolist(), "offset_m": off[:, :2].tolist(),
            "shrink": off[:, 2:4].tolist() if model.extent else None,
            "shear": off[:, 4].tolist() if model.shear else None}
