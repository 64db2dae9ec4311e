"""Where a fitted surface is seen, and where its error bars stop holding: the surface mask and
the edge map of ``fit_surface`` (step 5 of ``fit.py``'s docstring)."""
from __future__ import annotations

import numpy as np

from .grid import DepthGrid

__all__ = ["BRIGHT", "bright_nodes", "neighbourhood_mean", "surface_mask", "edge_map", "cut_cells", "depth_step",
           "EDGE_FACTOR", "EDGE_DEPTH_FLOOR", "EDGE_ALBEDO_FLOOR", "EDGE_ALBEDO_FLOOR_PRIOR",
           "EDGE_ROUGHNESS", "edge_albedo_floor", "edge_std", "edge_note"]


#: a lit node's albedo is at least this fraction of the surface's bright albedo (``bright_nodes``)
BRIGHT = 0.1


def bright_nodes(rho, rho_std, z: float) -> np.ndarray:
    """Nodes whose albedo is at least ``BRIGHT`` of the surface's bright albedo: the 90th
    percentile of the albedos significant at ``z`` std on their own (of all positive ones when
    none is). Not the single largest albedo: a node far off the surface trades albedo for its
    range (a return falls as 1/d^4 in a confocal scan) and one such node set the scale for all.
    Measured on the Stanford 40 cm dot chart (12 x 12 nodes): a grid corner fitted at 0.77 m, the
    dots at 0.41 m, held the largest albedo; with 2 x 2 sub-samples per cell (step 4d of
    ``fit.py``) it rose to 5-10 times the dots' and the mask fell from 25 nodes to 5."""
    r = np.asarray(rho, float)
    sd = np.asarray(rho_std, float)
    sig = r > z * sd
    pool = r[sig] if sig.any() else r[r > 0]
    if pool.size == 0:
        return np.zeros(r.shape, bool)
    return r > BRIGHT * float(np.percentile(pool, 90))


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


def surface_mask(grid: DepthGrid, rho, rho_std, C_rho, z: float, evidence=None):
    """Nodes where the data see a surface: albedo at least a tenth of the surface's bright albedo
    (``bright_nodes``), and significant
    at ``z`` std on its own or as the mean of its 3 x 3 neighbourhood (std from the albedos' full
    covariance ``C_rho``). On a grid finer than the data resolve, neighbouring albedos are
    anticorrelated and each node's own std is large while their mean is well determined: the
    tilted-plane twin with 12 x 12 nodes over 8 x 8 traces had 21 of its 64 support nodes
    significant on their own.

    ``evidence`` (per node, the chi^2 rise when its albedo alone is set to zero, divided by the
    inflation: ``prune.node_evidence``): where given, a node must also hold more than ``z``^2 of
    it. ``fit_surface`` gives it under the albedo's smoothness prior, whose smoothing spreads
    albedo a node beyond the surface's edge; the posterior calls that significant and the
    neighbourhood mean holds the bright side's: on the seeded study's scenes 1300-1323 under
    ``prior="auto"`` 81 of the masks' 969 nodes lay off the support (2 of 783 without a prior),
    40 of 923 with this test. The evidence there is the data's own: where the truth is dark it is
    negative (the data pull the albedo down, the prior up), clipped at zero."""
    Bn = neighbourhood_mean(grid)
    var = np.asarray(Bn.multiply(np.asarray(Bn @ C_rho)).sum(axis=1)).ravel()     # diag(Bn C Bn^T)
    nb_z = (Bn @ rho) / np.sqrt(np.maximum(var, 1e-300))
    seen = bright_nodes(rho, rho_std, z) & ((rho > z * rho_std) | (nb_z > z))
    return seen if evidence is None else seen & (np.asarray(evidence, float) > z * z)


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
    albedo, a letter's bar two cells wide trading albedo across its width). Without the cut
    cells' centroids (``cuts.py``) the error reached beyond this band on paired relays at noise
    below about 0.5 %; with them the band's own numbers lie within 2 std for 88 % on held-out
    scenes (BENCHMARKS.md, "Surface fit on seeded random twins"), and the fit widens the band's
    std for the rest (``edge_std``)."""
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


#: the edge nodes' std (``edge_std``): their Fisher std times EDGE_FACTOR and, in quadrature, the
#: edge model's own error, which does not fall with the noise: EDGE_DEPTH_FLOOR x the cell pitch in
#: depth; in albedo the larger of EDGE_ALBEDO_FLOOR x the mask's bright albedo (its 90th
#: percentile; EDGE_ALBEDO_FLOOR_PRIOR where the albedo std are the posterior's under the
#: albedo's smoothness prior, whose pull toward the dark outside is a bias they do not hold; the
#: data's std under the prior, the default, hold it with EDGE_ALBEDO_FLOOR: seeds 1300-1323
#: under prior "auto" gave 18 OK / 6 FLAGGED / 0 SILENT-WRONG with either floor, their claims
#: 0.996 of 738 within 2 std) and EDGE_ROUGHNESS x the node's departure from the mean
#: albedo of the mask nodes in its 3 x 3 neighbourhood (neighbours trading albedo). Calibrated on
#: the seeded study's scenes 1100-1123 (prior none and auto) and the failures of 1200-1223;
#: judged on 1300-1323 (BENCHMARKS.md, "Edge nodes' error bars").
EDGE_FACTOR = 1.0
EDGE_DEPTH_FLOOR = 0.01
EDGE_ALBEDO_FLOOR = 0.05
EDGE_ALBEDO_FLOOR_PRIOR = 0.25
EDGE_ROUGHNESS = 1.0


def edge_albedo_floor(prior: bool) -> float:
    """The edge albedo floor's fraction of the bright albedo: EDGE_ALBEDO_FLOOR_PRIOR where the
    albedos were fitted under their smoothness prior and their std are the posterior's
    (``prior``), else EDGE_ALBEDO_FLOOR."""
    return EDGE_ALBEDO_FLOOR_PRIOR if prior else EDGE_ALBEDO_FLOOR


def edge_std(edge, mask, z_std, rho, rho_std, n_std, pitch: float, factor: float = EDGE_FACTOR,
             depth_floor: float = EDGE_DEPTH_FLOOR, albedo_floor: float | None = None,
             roughness: float = EDGE_ROUGHNESS, prior: bool = False):
    """The std of the edge nodes (``edge_map``) widened by the error of the edge's model: a cell
    the surface's edge cuts is modelled as uniform (or, with ``cuts.py``, by its covered part's
    centroid and extents), and it and its neighbours trade depth and albedo with the part the
    model cannot hold. That error does not fall with the noise: with the Fisher std alone, edge
    nodes of the seeded study lay up to 14 std off at low noise (seed 1211, two bars 3 cells wide,
    0.3 % noise: each bar's outer column -0.15 to -0.24 in albedo, its inner column +0.14 to +0.22,
    at std 0.013-0.06; seed 1107, a cap: +0.06 at std 0.01). So each edge node's std is
    ``hypot(factor * std, floor)``: depth floor ``depth_floor`` x ``pitch`` (the cell's side, m);
    albedo floor the larger of ``albedo_floor`` (None: EDGE_ALBEDO_FLOOR, or EDGE_ALBEDO_FLOOR_PRIOR
    where ``prior``: the albedos were fitted under their smoothness prior, their std the
    posterior's) x the mask's bright albedo (the 90th percentile of its albedos: a fraction of
    the surface's own reflectance, absolute or relative) and ``roughness`` x |albedo - the mean
    albedo of the mask nodes in its 3 x 3 neighbourhood| (a trade shows as neighbours alternating
    about their mean); each normal's std grows by its depth std's ratio (the normals follow from
    the depths). Nodes off the edge keep their std.

    ``edge`` and ``mask`` are (ny, nx); the other arrays flat over the N nodes (``n_std`` (N,
    3)). Returns new (z_std, rho_std, n_std)."""
    from scipy.ndimage import convolve

    e2 = np.asarray(edge, bool)
    e = e2.ravel()
    z_std, rho_std = np.asarray(z_std, float).copy(), np.asarray(rho_std, float).copy()
    n_std = np.asarray(n_std, float).copy()
    if not e.any():
        return z_std, rho_std, n_std
    m2 = np.asarray(mask, bool).reshape(e2.shape)
    r2 = np.asarray(rho, float).reshape(e2.shape)
    bright = float(np.percentile(r2[m2], 90)) if m2.any() else float(np.max(np.abs(r2[e2])))
    if albedo_floor is None:
        albedo_floor = edge_albedo_floor(prior)
    k3 = np.ones((3, 3))
    w = m2.astype(float)
    mean = convolve(r2 * w, k3, mode="constant") / np.maximum(convolve(w, k3, mode="constant"), 1.0)
    floor_a = np.maximum(albedo_floor * max(bright, 0.0), roughness * np.abs(r2 - mean)).ravel()
    z_new = np.hypot(factor * z_std[e], depth_floor * float(pitch))
    n_std[e] *= (z_new / np.maximum(z_std[e], 1e-300))[:, None]
    z_std[e] = z_new
    rho_std[e] = np.hypot(factor * rho_std[e], floor_a[e])
    return z_std, rho_std, n_std


def edge_note(n_edge: int, n_mask: int, model, widened: bool, prior: bool = False) -> str:
    """The fit's note on its edge nodes: how many, what the edge's model leaves out (``model``:
    the ``SurfaceModel`` with its cut cells' centroids ``K`` and ``extent``), and whether their
    std were widened by ``edge_std`` (``widened``; ``prior``: as for albedos fitted under their
    smoothness prior with the posterior's std) or hold the noise only."""
    albedo_floor = edge_albedo_floor(prior)
    how = (f"the cut cells' centroids{' and extents per side' if model.extent else ''} are fitted, not the rest "
           "of the covered part's shape" if model.K else "a partly covered cell is modelled as uniform")
    head = (f"{n_edge} of the {n_mask} mask nodes lie at the surface's edge (SurfaceResult.edge: a cell the edge "
            "may cut, or its neighbour)")
    if widened:
        return (f"{head}: their std are widened for the error of the edge's model ({how}): "
                f"hypot({EDGE_FACTOR:g} x Fisher std, floor), floors {EDGE_DEPTH_FLOOR:g} x the cell pitch in depth "
                f"and in albedo the larger of {albedo_floor:g} x the mask's bright albedo and the node's departure "
                "from its mask neighbours' mean (mask.edge_std)")
    return f"{head}: their std hold the noise only, not the error of the edge's model ({how}; edge_std_model=False)"


def shifted_pair(shape, dy: int, dx: int):
    """Slices (a, b) of an (ny, nx) map such that ``m[a]`` and ``m[b]`` pair every node with its
    neighbour ``dy`` rows down and ``dx`` columns across (dy >= 0); None where no node has one."""
    ny, nx = shape
    y1, x0, x1 = ny - dy, max(0, -dx), min(nx, nx - dx)
    if y1 <= 0 or x1 <= x0:
        return None
    return (slice(0, y1), slice(x0, x1)), (slice(dy, y1 + dy), slice(x0 + dx, x1 + dx))


def depth_step(mask: np.ndarray, z: np.ndarray, z_std: np.ndarray, hx: float, hy: float,
               reach: int = 2, slope: float = 0.7, labels: np.ndarray | None = None,
               parts: np.ndarray | None = None):
    """The steepest depth step between two separate parts of the mask (8-connected components)
    at most ``reach`` nodes apart: pairs whose depth difference, less 3 std of it (the two std
    in quadrature), exceeds ``slope`` times their lateral distance (0.7: 35 deg, above the study's
    planes, tilted at most 30 deg, and its caps, 30 deg at their rim). A node's normal comes from
    its two neighbours' depths (central differences): two parts two nodes apart share the node
    between them, which cannot take both depths, so one part's normals tilt toward the other (on
    two bars 11 cm apart in depth the fit reached chi2/dof 1.023 with a claim 9 std off: seed 501
    of the study); three or more nodes apart, each side's neighbour takes its own depth and the
    height field holds both (``tests/test_nlos_explained.py``: two bars 12 cm apart with a gap of
    two nodes, explained). A steep surface in one piece is not a step. ``labels``: the grid's
    separate height fields (``DepthGrid.labels``); a step between two of them is modelled, not
    reported. ``parts``: the mask's parts given (integers, 0 outside them) instead of its
    8-connected components (``steps.step_labels``: parts linked only by gentle slopes).

    Returns None, or a dict with the pair's nodes (row-major), lateral distance, depth difference
    and its slope."""
    from scipy.ndimage import label

    m = np.asarray(mask, bool)
    if parts is None:
        lab, n_parts = label(m, structure=np.ones((3, 3), bool))
    else:
        lab = np.where(m, np.asarray(parts).reshape(m.shape), 0)
        n_parts = len(np.unique(lab[m]))
    if n_parts < 2:
        return None
    ny, nx = m.shape
    L = None if labels is None else np.asarray(labels).reshape(m.shape)
    best = None
    for dy in range(0, reach + 1):
        for dx in range(-reach, reach + 1):
            if (dy == 0 and dx <= 0) or max(abs(dx), dy) > reach:
                continue
            pair = shifted_pair(m.shape, dy, dx)
            if pair is None:
                continue
            a, b = pair
            y0, x0 = a[0].start, a[1].start
            apart = m[a] & m[b] & (lab[a] != lab[b])
            if L is not None:
                apart &= L[a] == L[b]
            if not apart.any():
                continue
            d = float(np.hypot(dx * hx, dy * hy))
            excess = np.abs(z[a] - z[b]) - 3.0 * np.hypot(z_std[a], z_std[b]) - slope * d
            excess = np.where(apart, excess, -np.inf)
            k = np.unravel_index(int(np.argmax(excess)), excess.shape)
            if excess[k] > 0 and (best is None or excess[k] / d > best["excess"] / best["distance"]):
                i = (k[0] + y0) * nx + (k[1] + x0)
                j = (k[0] + y0 + dy) * nx + (k[1] + x0 + dx)
                dz = float(abs(z[a][k] - z[b][k]))
                best = {"nodes": [int(i), int(j)], "distance": d, "dz": dz, "slope": dz / d,
                        "limit": slope, "excess": float(excess[k])}
    return best
