"""Nodes the data give no evidence of: step 4b of ``fit.py``.

When to use: called by ``fit_surface`` after its last level's solve (``SurfaceSettings.prune``);
nothing else needs it.

The grid spans the initialiser's support grown by a margin, so most of its nodes lie off the
surface. Their albedos fit noise (specks of a few per cent up to the bound 1 at depths whose
returns barely reach the window), their depths are barely determined, and every LM step moves
them by the slack far into the response's nonlinear range: on held-out study scenes the steps
then lowered chi^2 by 0.05-0.4 of what their quadratic model predicted, and LM crawled to its
iteration limit with the surface itself still 0.5-1.6 std from its optimum (measured on seed
604: the grid's 127 off-surface nodes each explained chi^2 0-24, the 17 surface nodes 290-950).

The evidence of node i is the rise of chi^2 when its albedo is set to zero with every other
unknown held, e_i = rho_i^2 H_ii - 2 rho_i g_i (exact: the model is linear in the albedos), an
upper bound on the rise after the others are refitted. Nodes with e_i below the chi^2 quantile of
2 degrees of freedom at p = ``PRUNE_P`` (9.21; the statistic divided by the inflation
max(1, chi2/dof)) get albedo 0, held there (their depth too where no neighbour
is lit: ``SurfaceModel.seen``), the level is solved again from its solution, and the pruned model
is kept unless the likelihood ratio of the two nested models exceeds the chi^2 quantile of the
unknowns removed at p = ``PRUNE_P`` (the pruned nodes then explain signal jointly: the full
model stands; ``lm.nested_lr``, the full model's inflation). The ratio uses the full model's solve as it stopped; where that solve had not
converged its chi^2 is above its optimum and the ratio is too small by the decrease left (the
remaining step's, a few units on the study's scenes, against thresholds of ~100-300). With
``early`` the pruned solve stops once its F is as low as the full solve's (the ratio at most 0,
and it only falls as the solve goes on, so the decision is a finished solve's): that happens only
where the full solve stopped at its iteration limit; the caller (step 4c) solves on from there. A
target at the test's threshold instead (F_full + threshold x inflation / 2) stopped seed 808 of the
study after one iteration, 4c's solve then ended in a worse optimum (F 3607.8 against 3598.7) and
the fit SILENT-WRONG.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.stats import chi2 as _chi2_dist

from .lm import nested_lr

__all__ = ["PRUNE_P", "node_evidence", "prune_nodes"]

#: level of the pruning tests: a node is pruned when its evidence is below the chi^2(2) quantile
#: at PRUNE_P (a node that only fits noise falls below it with probability 0.99; not divided
#: over the nodes: Bonferroni's ~19 on a 12 x 12 grid would prune nodes 3-4.4 std on their own),
#: and the pruned model is kept when the nodes together do not explain more than chance would at
#: PRUNE_P
PRUNE_P = 0.01


def node_evidence(rho: np.ndarray, g: np.ndarray, h_diag: np.ndarray) -> np.ndarray:
    """The rise of chi^2 when each node's albedo alone is set to zero, rho^2 H_ii - 2 rho g_i
    (``g``, ``h_diag``: the albedos' entries of the gradient of chi^2 / 2 and of J^T W J)."""
    rho = np.asarray(rho, float)
    return np.maximum(rho * rho * np.asarray(h_diag, float) - 2.0 * rho * np.asarray(g, float), 0.0)


def prune_nodes(state, res: dict, lin: dict, y, wgt, model, set_pruned, make_bounds, solve,
                early: bool = False) -> dict | None:
    """The level solved again with the nodes of no evidence pruned, from ``state`` (the solution
    ``res`` of the level's own solve; ``lin``: ``model.linearise`` there, with H).
    ``set_pruned(mask)``: makes ``make_bounds`` hold those nodes' albedos at zero;
    ``solve(model, bounds, state)``: the level's solver. ``early``: the pruned solve stops once
    its F is as low as the full solve's (``solve(..., f_stop=F)``): the ratio is then at most 0
    and only falls as the solve goes on, so the decision is a finished solve's; it stops only
    where the full solve had not converged, leaving its state unsettled (``info["settled"]``
    False: the caller solves on from it, step 4c).

    Returns None (no node to prune), or a dict: ``info`` (``nodes`` pruned, ``lit`` of them with
    an albedo above zero, the likelihood ratio ``lr``, its ``threshold`` at ``p``, ``kept``, the
    per-node ``node_threshold``, the solve's ``status`` and ``iterations``), the solve's ``res``
    and ``bounds``, and ``mask`` (the pruned nodes; all False when not kept)."""
    N = model.N
    n_y = int(np.size(y))
    infl = max(1.0, float(lin["chi2"]) / max(n_y - model.npar, 1))
    H, g = lin["H"], lin["g"]
    ev = node_evidence(state.rho, g[N:2 * N], np.diag(H)[N:2 * N]) / infl
    node_thr = float(_chi2_dist.isf(PRUNE_P, 2))
    cut = ev < node_thr
    seen0 = model.seen(state.rho)
    if not cut.any() or cut.all():
        return None
    rho = np.where(cut, 0.0, state.rho)
    s0 = replace(state, rho=rho)
    # the unknowns removed: the lit pruned nodes' albedos and the depths no longer seen
    removed = int(np.sum(cut & (state.rho > 0))) + int(np.sum(seen0 & ~model.seen(rho)))
    set_pruned(cut)
    bounds = make_bounds(model)
    if early:       # at the full solve's F: lr <= 0, and the pruned solve has caught up with it
        out = solve(model, bounds, s0, f_stop=float(res["f"]))
    else:
        out = solve(model, bounds, s0)
    lr, need = nested_lr(out["f"], res["f"], lin["chi2"], n_y - model.npar, removed, PRUNE_P)
    kept = bool(lr <= need)
    if not kept:
        set_pruned(np.zeros(N, bool))
    info = {"nodes": int(cut.sum()), "lit": int(np.sum(cut & (state.rho > 0))), "removed_unknowns": removed,
            "lr": lr, "threshold": need, "p": PRUNE_P, "node_threshold": node_thr, "kept": kept,
            "evidence_max_pruned": float(ev[cut].max()), "status": out["status"], "iterations": out["iterations"],
            "settled": out["status"] != "Target reached"}
    return {"info": info, "res": out, "bounds": bounds if kept else make_bounds(model),
            "mask": cut if kept else np.zeros(N, bool)}
