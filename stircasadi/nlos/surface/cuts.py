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
the centroids (``lm.nested_lr``); else the uniform cells stand.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from .lm import nested_lr
from .mask import cut_cells

__all__ = ["CUT_P", "fit_cut_cells"]

#: false-alarm probability of the likelihood-ratio test that keeps the cut cells' centroids:
#: the nested model with 2 K more unknowns must lower chi^2 by more than chance would
CUT_P = 0.01


def fit_cut_cells(shape, state, res: dict, y, wgt, make_model, make_bounds, solve) -> dict | None:
    """The level solved again with its cut cells' centroids free, from ``state`` (the solution
    ``res`` of the level's own solve). ``make_model(nodes)``: the level's model with those
    offset nodes; ``make_bounds(model)``; ``solve(model, bounds, state)``: the level's solver.

    Returns None (no cell cut), or a dict: ``info`` (nodes, the likelihood ratio ``lr``, its
    ``threshold`` at ``p``, ``kept``, the solve's ``status`` and ``iterations``) and that solve's
    ``model``, ``bounds`` and ``res``."""
    band = cut_cells(np.asarray(state.rho).reshape(shape))
    if not band.size:
        return None
    model = make_model(band)
    bounds = make_bounds(model)
    out = solve(model, bounds, replace(state, off=np.zeros((band.size, 2))))
    chi2 = float(model.objective(out["state"], y, wgt)[0])
    lr, need = nested_lr(res["f"], out["f"], chi2, int(np.size(y)) - model.npar, 2 * band.size, CUT_P)
    info = {"nodes": int(band.size), "lr": lr, "threshold": need, "p": CUT_P, "kept": bool(lr > need),
            "status": out["status"], "iterations": out["iterations"]}
    return {"info": info, "model": model, "bounds": bounds, "res": out}
