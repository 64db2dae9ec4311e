"""What the levels of ``fit.py`` start from: the first level's surface from a volumetric
initialiser's maps (step 1), the starting response and each level's time window.

When to use: called by ``fit_surface``; nothing else needs it.
"""
from __future__ import annotations

import math

import numpy as np

from ...irf import GaussianIRF
from ..relay import Relay
from ..volume import Maps
from .direct import direct_return
from .grid import DepthGrid
from .response import Response
from .settings import SurfaceSettings

__all__ = ["support", "initial", "extent", "response0", "window"]


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


def response0(relay: Relay, st: SurfaceSettings, gate):
    """The starting response and the direct return's per-trace amplitude (or None): the
    relay's Gaussian IRF; else the response measured on the relay's direct return
    (``direct.py``); else a single-photon emg of 1.5 bins."""
    irf = relay.irf
    gauss = isinstance(irf, GaussianIRF)
    if st.response == "auto" and not gauss and st.direct != "none":
        dr = direct_return(relay, gate)
        if dr is not None:
            r = dr.response
            if st.sigma0 is not None or st.tail0 is not None:
                r = r.with_params(st.sigma0 or r.sigma, st.tail0 if r.kind == "emg" else None)
            return r, dr.q
    kind = st.response if st.response != "auto" else ("gaussian" if gauss else "emg")
    if st.sigma0 is not None:
        sig = float(st.sigma0)
    elif irf is not None and getattr(irf, "sigma", 0) > 0:
        sig = float(irf.sigma) / (1.0 if kind == "gaussian" else math.sqrt(2.0))
    else:
        sig = 1.5 * relay.grid.bin_width
    tail = (float(st.tail0) if st.tail0 is not None else 2.0 * sig) if kind == "emg" else 0.0
    return Response(kind, sig, tail), None


def window(relay: Relay, grid: DepthGrid, z0, resp_hi: Response, cell: float, pad: float, gate,
            slow_pad: float = 0.0):
    """The relay cut to the bins the level's paths can reach (chunked over traces)."""
    X, _, _ = grid.geometry(z0)
    lo_d, hi_d = np.inf, -np.inf
    for t0 in range(0, relay.n_traces, 256):
        sl = slice(t0, t0 + 256)
        d = (np.linalg.norm(relay.L[sl, None] - X[None], axis=-1)
             + np.linalg.norm(relay.D[sl, None] - X[None], axis=-1) + relay.leg[sl, None])
        lo_d, hi_d = min(lo_d, float(d.min())), max(hi_d, float(d.max()))
    a, b = resp_hi.support(math.sqrt(resp_hi.sigma ** 2 + cell ** 2))
    lo = max(lo_d + a - pad, gate if gate is not None else -np.inf)
    return relay.window(lo, hi_d + b + pad + slow_pad)
