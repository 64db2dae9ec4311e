"""Shared fixtures for the symbolic-model and estimation tests (seeded, small)."""
from __future__ import annotations

import numpy as np

from stircasadi.estimate import EstimateSettings
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


def hidden_model(sc, gr, irf, d_offsets=None, eps=0.03, albedo0=0.5):
    """Hidden-corner model with hidden distances unknown, starting at truth + d_offsets."""
    m = TransientModel.from_scene(sc, gr, irf)
    m.set_unknown("albedo", "all", initial=albedo0)
    h = np.flatnonzero(sc.hidden)
    vis = np.flatnonzero(~sc.hidden)[:2]
    true_d = np.array([[np.linalg.norm(sc.positions[k] - sc.positions[a]) for a in vis] for k in h])
    off = np.zeros_like(true_d) if d_offsets is None else np.asarray(d_offsets, float)
    for i, k in enumerate(h):
        m.set_hidden_distances(k, vis, eps=eps, initial=true_d[i] + off[i])
    return m, h, true_d
