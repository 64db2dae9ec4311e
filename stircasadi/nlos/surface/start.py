"""The first level's surface from a volumetric initialiser's maps (step 1 of ``fit.py``).

When to use: called by ``fit_surface``; nothing else needs it.
"""
from __future__ import annotations

import numpy as np

from ..volume import Maps
from .grid import DepthGrid
from .settings import SurfaceSettings

__all__ = ["support", "initial", "extent"]


def support(maps: Maps, st: SurfaceSettings) -> np.ndarray:
    """Columns of the initialiser that hold a surface: its mask or an albedo of at least
    ``init_fraction`` of the largest (a volume's mask keeps only columns far above the median,
    which on a scan full of returns leaves most of the object out)."""
    return maps.mask | (maps.albedo >= st.init_fraction * max(float(maps.albedo.max()), 1e-300))


def initial(maps: Maps, grid: DepthGrid, st: SurfaceSettings):
    """Depths and albedos on ``grid``: the initialiser's where it holds a surface (``support``),
    the median of those depths and 5 % of the largest albedo elsewhere."""
    sup = support(maps, st)
    d = np.where(sup, maps.depth, np.median(maps.depth[sup]) if sup.any() else np.median(maps.depth))
    src = DepthGrid(maps.x, maps.y, maps.frame)
    z0 = src.resample(d, grid)
    a0 = src.resample(np.where(sup, maps.albedo, 0.05 * maps.albedo.max()), grid)
    return z0, np.clip(a0, 0.0, None)


def extent(maps: Maps, st: SurfaceSettings):
    """The grid's (x0, x1, y0, y1): ``st.extent``, else the support's bounding box grown by
    ``st.margin`` of its size (at least one initialiser cell) per side."""
    if st.extent is not None:
        return st.extent
    m = support(maps, st)
    m = m if m.any() else np.ones_like(m)
    iy, ix = np.nonzero(m)
    x0, x1 = maps.x[ix.min()], maps.x[ix.max()]
    y0, y1 = maps.y[iy.min()], maps.y[iy.max()]
    gx = max(st.margin * (x1 - x0), maps.x[1] - maps.x[0])
    gy = max(st.margin * (y1 - y0), maps.y[1] - maps.y[0])
    return (x0 - gx, x1 + gx, y0 - gy, y1 + gy)
