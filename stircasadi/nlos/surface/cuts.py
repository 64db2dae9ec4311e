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
"""
from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from .lm import _damping, _free, nested_lr, prior_gradient, prior_penalty
from .mask import cut_cells

__all__ = ["CUT_P", "fit_cut_cells", "restricted_optimum"]

#: false-alarm probability of the likelihood-ratio test that keeps the cut cells' centroids:
#: the nested model with 2 K more unknowns must lower chi^2 by more than chance would
CUT_P = 0.01


def restricted_optimum(model, bounds, lin: dict, state, lam: float, R) -> float:
    """F = chi^2 / 2 + prior at the optimum of the model without the cut cells' centroids,
    estimated from ``model``'s linearisation ``lin`` at ``state`` (centroids zero: there the
    model is the one without them): F at ``state`` less half the decrease of 2F that the undamped
    Gauss-Newton step on the other free unknowns predicts (``lm._free``: the projected step LM
    makes; 2F is the whitened chi^2 plus the prior's penalty): low where the quadratic model
    overpromises, high where it underpromises."""
    N, M = model.N, R.shape[0]
    H, g = np.array(lin["H"], float), prior_gradient(lin["g"], state, lam, R)
    f = 0.5 * float(lin["chi2"]) + prior_penalty(state, lam, R)
    if lam > 0:
        H[:M, :M] += lam * R
    lo, hi = bounds.lo.copy(), bounds.hi.copy()
    if model.K:
        lo[-2 * model.K:] = hi[-2 * model.K:] = 0.0     # the centroids held: not free
    b = SimpleNamespace(lo=lo, hi=hi)
    fi, d = _free(model, state, model.pack(state), H, g, b, _damping(np.diag(H), N, hi[N:2 * N] <= 0.0))
    return f - 0.5 * max(-float(g[fi] @ d), 0.0) if len(fi) else f


def fit_cut_cells(shape, state, res: dict, y, wgt, make_model, make_bounds, solve, settle=None,
                  quad: dict | None = None) -> dict | None:
    """The level solved again with its cut cells' centroids free, from ``state`` (the solution
    ``res`` of the level's own solve). ``make_model(nodes)``: the level's model with those
    offset nodes; ``make_bounds(model)``; ``solve(model, bounds, state, lin0=None)``: the level's
    solver.

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
    ratio was taken against, the solve's ``status`` and ``iterations``), that solve's
    ``model``, ``bounds`` and ``res``, and ``restricted``: the settled solve (None unless made)."""
    band = cut_cells(np.asarray(state.rho).reshape(shape))
    if not band.size:
        return None
    model = make_model(band)
    bounds = make_bounds(model)
    s0 = replace(state, off=np.zeros((band.size, 2)))
    lin0, f_ref, ref, settled = None, float(res["f"]), "solve", None
    if settle is not None:
        s0 = model.unpack(bounds.project(model.pack(s0)), s0)
        held = bounds.hi[model.N:2 * model.N] <= 0.0
        lin0 = model.linearise(s0, y, wgt, dtype=quad["dtype"], skip=held if held.any() else None)
        f_ref = restricted_optimum(model, bounds, lin0, s0, quad["lam"], quad["R"])
        f_ref, ref = min(f_ref, float(quad.get("floor", np.inf))), "estimate"
    out = solve(model, bounds, s0, lin0=lin0)
    chi2 = float(model.objective(out["state"], y, wgt)[0])
    dof = int(np.size(y)) - model.npar
    lr, need = nested_lr(f_ref, out["f"], chi2, dof, 2 * band.size, CUT_P)
    if settle is not None and lr <= need:
        settled = settle()
        f_ref, ref = float(settled["f"]), "solve"
        lr, need = nested_lr(f_ref, out["f"], chi2, dof, 2 * band.size, CUT_P)
    info = {"nodes": int(band.size), "lr": lr, "threshold": need, "p": CUT_P, "kept": bool(lr > need),
            "reference": ref, "f_reference": f_ref, "status": out["status"], "iterations": out["iterations"]}
    return {"info": info, "model": model, "bounds": bounds, "res": out, "restricted": settled}
