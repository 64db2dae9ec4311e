"""Two surfaces side by side at different depths: step 4a of ``fit.py`` (after the last level's
first solve, before pruning and the cut cells).

When to use: called by ``fit_surface`` after its last level's solve
(``SurfaceSettings.split_steps``); nothing else needs it.

One height field over two objects at different depths with one node or two between them cannot
hold both: the node between them enters both parts' central differences, so one part's normals
tilt toward the other, an error the std do not hold (``mask.depth_step`` then fails the fit).
The lit nodes (albedo above a tenth of the largest) are grouped into parts by links between
8-neighbours whose depths differ by at most ``SLOPE`` times their distance (a surface in one
piece stays one part; the nodes of a gap between two objects, whose cells the two edges both
cut, take depths between theirs and fall into dim parts of their own); when two parts of at
least ``MIN_PART`` nodes whose summed albedo is at least ``MIN_SHARE`` of the brightest part's
(a surface, not a speck of noise or a strip of cells both edges cut) have a depth step between
them (``mask.depth_step`` on those parts, before any std exist), every node takes the label of
its nearest such part (Euclidean distance over the grid) and the grid becomes a labelled one
(``DepthGrid.labels``: no difference operator, and no smoothness prior, crosses a label's
border); the level is solved again from its solution, and the split is kept when its F (chi^2 /
2 plus prior) ends below the single field's (the two models have the same unknowns; neither is
nested in the other).
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .mask import depth_step, shifted_pair

__all__ = ["MIN_PART", "MIN_SHARE", "SLOPE", "smooth_parts", "step_labels"]

#: the fewest nodes of a part that may be split off
MIN_PART = 3
#: the smallest summed albedo of a part that may be split off, relative to the brightest part's
MIN_SHARE = 0.25
#: the steepest slope between two neighbours of one part (``mask.depth_step``'s 35 deg)
SLOPE = 0.7


def smooth_parts(lit: np.ndarray, z: np.ndarray, hx: float, hy: float, slope: float = SLOPE) -> np.ndarray:
    """Parts of the ``lit`` nodes (ny, nx) linked through 8-neighbours whose depth difference is
    at most ``slope`` times their lateral distance: integers 1.. in each part, 0 off ``lit``."""
    ny, nx = lit.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    rows, cols = [], []
    for dy, dx in ((0, 1), (1, -1), (1, 0), (1, 1)):
        pair = shifted_pair(lit.shape, dy, dx)
        if pair is None:
            continue
        a, b = pair
        ok = lit[a] & lit[b] & (np.abs(z[a] - z[b]) <= slope * np.hypot(dx * hx, dy * hy))
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    g = coo_matrix((np.ones(r.size), (r, c)), shape=(ny * nx, ny * nx))
    _, comp = connected_components(g, directed=False)
    out = np.zeros(ny * nx, int)
    keys = np.unique(comp[lit.ravel()])
    out[lit.ravel()] = np.searchsorted(keys, comp[lit.ravel()]) + 1
    return out.reshape(ny, nx)


def step_labels(shape, z: np.ndarray, rho: np.ndarray, hx: float, hy: float) -> np.ndarray | None:
    """Labels (N,) of the nearest part of every node when two parts (``smooth_parts``) of at least
    ``MIN_PART`` nodes and ``MIN_SHARE`` of the brightest part's summed albedo have a depth step
    between them (``mask.depth_step`` without std); else None."""
    rho = np.asarray(rho, float).reshape(shape)
    zz = np.asarray(z, float).reshape(shape)
    lit = rho > 0.1 * max(float(rho.max()), 1e-300)
    parts = smooth_parts(lit, zz, hx, hy)
    sizes = np.bincount(parts.ravel())
    light = np.bincount(parts.ravel(), weights=rho.ravel())
    light[0] = 0.0
    ok = (sizes >= MIN_PART) & (light >= MIN_SHARE * light.max())
    ok[0] = False
    big = ok[parts]
    keys = np.unique(parts[big])
    if len(keys) < 2 or depth_step(big, zz, np.zeros(shape), hx, hy, slope=SLOPE, parts=parts) is None:
        return None
    _, (iy, ix) = distance_transform_edt(~big, sampling=(hy, hx), return_indices=True)
    return np.searchsorted(keys, parts[iy, ix]).ravel()
