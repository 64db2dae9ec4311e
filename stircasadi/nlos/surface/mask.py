"""Where a fitted surface is seen, and where its error bars stop holding: the surface mask and
the edge map of ``fit_surface`` (step 5 of ``fit.py``'s docstring)."""
from __future__ import annotations

import numpy as np

from .grid import DepthGrid

__all__ = ["neighbourhood_mean", "surface_mask", "edge_map", "cut_cells"]


def neighbourhood_mean(grid: DepthGrid):
    """Sparse (N, N) operator: the mean over each node's 3 x 3 neighbourhood (the nodes of the
    grid among them; nodes are row-major over (y, x), so the neighbourhood is the Kronecker
    product of the two axes' tridiagonal ones)."""
    import scipy.sparse as sp
    ny, nx = grid.shape

    def tri(n):
        return sp.diags([np.ones(n - 1), np.ones(n), np.ones(n - 1)], [-1, 0, 1])

    B = sp.kron(tri(ny), tri(nx), format="csr")
    return sp.diags(1.0 / np.asarray(B.sum(axis=1)).ravel()) @ B


def surface_mask(grid: DepthGrid, rho, rho_std, C_rho, z: float):
    """Nodes where the data see a surface: albedo at least a tenth of the largest, and significant
    at ``z`` std on its own or as the mean of its 3 x 3 neighbourhood (std from the albedos' full
    covariance ``C_rho``). On a grid finer than the data resolve, neighbouring albedos are
    anticorrelated and each node's own std is large while their mean is well determined: the
    tilted-plane twin with 12 x 12 nodes over 8 x 8 traces had 21 of its 64 support nodes
    significant on their own."""
    Bn = neighbourhood_mean(grid)
    var = np.asarray(Bn.multiply(np.asarray(Bn @ C_rho)).sum(axis=1)).ravel()     # diag(Bn C Bn^T)
    nb_z = (Bn @ rho) / np.sqrt(np.maximum(var, 1e-300))
    bright = rho > 0.1 * max(float(rho.max()), 1e-300)
    return bright & ((rho > z * rho_std) | (nb_z > z))


def cut_cells(rho: np.ndarray) -> np.ndarray:
    """Indices (row-major) of the nodes whose cell the surface's edge may cut, from a solved
    level's (ny, nx) albedo map: the support is where the albedos' 3 x 3 neighbourhood mean
    exceeds half its 90th percentile (over the means above a tenth of the largest; the mean,
    because on a grid finer than the data resolve neighbouring albedos alternate); the band is
    the support's inner ring (a support node with one of its eight neighbours outside it) and its
    outer ring where lit (a node outside beside one inside and an albedo above a quarter of the
    support's 90th percentile: at least about a quarter covered). These cells get a free
    centroid (``SurfaceModel(offset_nodes=...)``): a cut cell emits from its covered part.
    (Thresholds: with lit from a twentieth, seed 310 of the study had 42 such nodes where 31
    from a quarter, the dimmer cells' centroids barely moving the data, at their bounds, the
    solve stalled at its iteration limit; with the albedos themselves instead of their means,
    84 of 144 nodes of the 12 x 12 tilted-plane twin over 8 x 8 traces.)"""
    from scipy.ndimage import binary_dilation, convolve

    r = np.asarray(rho, float)
    if r.size == 0 or not float(r.max()) > 0:
        return np.zeros(0, int)
    k3 = np.ones((3, 3))
    mean = convolve(r, k3, mode="constant") / convolve(np.ones_like(r), k3, mode="constant")
    ref = float(np.percentile(mean[mean > 0.1 * mean.max()], 90))
    sup = mean > 0.5 * ref
    k = np.ones((3, 3), bool)
    outside = np.pad(~sup, 1, constant_values=False)        # the grid's border is not an edge
    inner = sup & binary_dilation(outside, structure=k)[1:-1, 1:-1]
    ref_r = float(np.percentile(r[sup], 90)) if sup.any() else float(r.max())
    outer = ~sup & binary_dilation(sup, structure=k) & (r > 0.25 * ref_r)
    return np.flatnonzero((inner | outer).ravel())


def edge_map(mask: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """(ny, nx) mask nodes at the surface's edge: cells the edge may cut (the mask's outer ring:
    next to a node outside the mask or the grid's border; or inside it with an albedo below half
    the mask's 90th percentile) and their eight neighbours. The model spreads each cell's albedo
    uniformly over it; a cell the support's edge cuts holds its surface off-centre, and its
    neighbours' albedos and depths trade with it, a model error the Fisher std do not hold
    (``benchmarks/surface_coverage.py``: full cells beside partly covered ones at 3-8 std in
    albedo, a letter's bar two cells wide trading albedo across its width). On paired relays at
    noise below about 0.5 % the error reaches beyond this band (BENCHMARKS.md, "Surface fit on
    seeded random twins")."""
    from scipy.ndimage import binary_dilation

    if not mask.any():
        return np.zeros_like(mask, bool)
    k = np.ones((3, 3), bool)
    out = np.pad(~mask, 1, constant_values=True)            # outside the mask or the grid
    # cells the edge may cut: the mask's outer ring (whatever their albedo: a cut cell holds any
    # fraction of its area) and, inside, any partly covered one (albedo below half the 90th
    # percentile, even where such cells outnumber the full ones)
    low = np.pad(mask & (rho < 0.5 * float(np.percentile(rho[mask], 90))), 1, constant_values=False)
    cut = binary_dilation(out, structure=k) | low
    return mask & binary_dilation(cut, structure=k)[1:-1, 1:-1]
