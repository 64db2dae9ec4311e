"""Shared fixtures for the symbolic-model and estimation tests (seeded, small)."""
from __future__ import annotations

import numpy as np

from stircasadi.joint import EstimateSettings
from stircasadi.model import TransientModel
from stircasadi.transport import simulate


def capture_of(mod, seed=0, sensor=None, scene=None, grid=None, **kw):
    sc = scene or mod.build_scene(**kw)
    gr = grid or mod.build_grid()
    se = sensor or mod.build_sensor()
    tr = simulate(sc, gr, se)
    return sc, gr, se, tr, se.capture(tr, seed=seed)


def quiet(**kw) -> EstimateSettings:
    s = EstimateSettings(**kw)
    s.ipopt.print_level = 0
    return s


def hidden_model(sc, gr, irf, offsets=None, eps=0.03, albedo0=0.5):
    """Hidden-corner model with hidden positions unknown in the scene's plane (y = 0), starting at
    truth + offsets ((n_hidden, 2): along x and z, metres)."""
    m = TransientModel.from_scene(sc, gr, irf)
    m.set_unknown("albedo", "all", initial=albedo0)
    h = np.flatnonzero(sc.hidden)
    basis = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])
    off = np.zeros((len(h), 2)) if offsets is None else np.asarray(offsets, float)
    for i, k in enumerate(h):
        m.set_unknown("position", [k], initial=sc.positions[k] + basis @ off[i], lower=-eps, upper=eps,
                      scale=eps, basis=basis)
    return m, h
