"""One trace chunk's Gauss-Newton matrix J^T W J for ``SurfaceModel.linearise``: the chunk's
Jacobian rows assembled densely over (z, rho, globals[, centroid offsets]) and multiplied by
BLAS syrk (``blas.gram_lower``).

When to use: called by ``SurfaceModel.linearise`` for each chunk; nothing else needs it.

The depth columns come from each window bin's six local derivatives (the node's patch z, gx,
gy, zxx, zyy, zxy) through the stacked difference operators in one sparse product; a bin of a
zero albedo has none (every patch derivative carries the albedo as a factor), so only the
``lit`` bins enter that product: the same matrix bit for bit, its zeros not formed.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .blas import gram_lower

__all__ = ["chunk_gram"]


def chunk_gram(model, nt, rows_loc, node, rows_lit, node_lit, dv, la, pre, post, wc, resp, dtype,
               zkeep=None) -> np.ndarray:
    """J^T W J of one chunk: dense rows over (z, rho, globals) (the chain rule through Gx,
    Gy maps the local gx, gy columns onto z; the slow tails filter the core's columns along
    time). Without slow tails only the rows some pair reaches are formed; the others carry
    only the background. ``rows_loc`` / ``node``: every window bin's chunk row and node;
    ``rows_lit`` / ``node_lit``: those of the bins whose patch derivatives were formed (a zero
    albedo's are zeros) and ``dv`` their local derivatives (patch unknowns, then any centroid
    offsets [shrinks]); ``la``: every bin's albedo derivative. ``zkeep``: the nodes whose depth
    column some lit bin reaches (None: all), the only depth columns formed: H over ``pack``'s
    unknowns less the other depths, in their order (the depths left out have exact zero
    columns)."""
    N, T = model.N, model.T
    nz = N if zkeep is None else len(zkeep)
    g0 = nz + N                           # the first global's column
    if resp.slow:
        ru = np.arange(nt * T)
    else:
        used = np.zeros(nt * T, bool)
        used[rows_loc] = True
        ru = np.flatnonzero(used)
    rmap = np.full(nt * T, -1)
    rmap[ru] = np.arange(len(ru))
    R = len(ru)
    rows = rmap[rows_loc]
    ng, npost = len(pre), len(post)
    K = model.K
    # the columns in ``pack``'s order: z, rho, the core's globals (pre), the others (post),
    # the centroid offsets; the post columns are set after the slow tails' filter (it does
    # not act on them: zero until then, they stay zero through it)
    C = g0 + ng + npost + model.E * K
    Jc = np.zeros((R, C), dtype=dtype)
    # depth columns: the six local derivatives of each window bin, a sparse (R, 6 N) matrix
    # (a pair's bin touches one node's six local unknowns), times the stacked operators
    # (I, Gx, Gy, Dxx, Dyy, Dxy) in one sparse product (its result is as sparse as the
    # nodes' stencils allow); albedo columns: one entry per window bin
    # (int32 indices: half the index traffic of the COO -> CSR conversion)
    rl = rmap[rows_lit]
    r32, n32 = rl.astype(np.int32), node_lit.astype(np.int32)
    cols = (n32[None] + np.int32(N) * np.arange(6, dtype=np.int32)[:, None]).ravel()
    Jl = sp.coo_matrix((dv[:6].ravel(), (np.tile(r32, 6), cols)), shape=(R, 6 * N)).tocsr()
    Jz = (Jl @ model.ops_stack).tocoo()
    del Jl
    if zkeep is None:
        Jc[Jz.row, Jz.col] = Jz.data
    else:
        zmap = np.full(N, -1)
        zmap[zkeep] = np.arange(nz)
        Jc[Jz.row, zmap[Jz.col]] = Jz.data
    del Jz
    Jc.ravel()[rows * C + nz + node] = la
    for i, c in enumerate(pre):
        Jc[:, g0 + i] = c.ravel()[ru]
    if K:    # the centroid offsets' columns (core columns: the slow tails filter them too)
        kmap = np.full(N, -1)
        kmap[model.onodes] = np.arange(K)
        kk = kmap[node_lit]
        on = kk >= 0
        base = rl[on] * C + g0 + ng + npost + model.E * kk[on]
        for e in range(model.E):
            Jc.ravel()[base + e] = dv[6 + e][on]
    if resp.slow:
        Jc = resp.tail_filter(Jc.reshape(nt, T, -1), model.w, axis=1).reshape(nt * T, -1)
    for i, c in enumerate(post):
        Jc[:, g0 + ng + i] = c.ravel()[ru]
    Jc *= np.sqrt(wc.ravel()[ru]).astype(dtype)[:, None]
    H = gram_lower(Jc)
    if not resp.slow:
        rest = np.ones(nt * T, bool)
        rest[ru] = False
        wr = wc.ravel()[rest]
        # the background columns of the rows no pair reaches (only "bg" is non-zero there
        # unless a direct-return decay is modelled: add its columns too)
        bi = [i for i, k in enumerate(model.glob) if k in ("bg", "bg1", "bgtau")]
        B = np.stack([p.ravel()[rest] for p in post[-len(bi):]], axis=1) if bi else None
        if B is not None:
            idx = g0 + np.array(bi)
            H = H.astype(np.float64)
            # (the lower triangle of the product's transpose: the entries the upper-triangle
            # sum of earlier versions took, so the numbers are unchanged)
            H[np.ix_(idx, idx)] += np.tril(((B * wr[:, None]).T @ B).T)
    return H
