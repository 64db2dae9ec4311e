"""Light paths of the symbolic model: legs between vertices, paths of 1..K bounces, time windows.

Enumerated once, numerically, at the initial geometry (visibility and mirror hits do not change
as unknowns move). A leg joins two vertices directly (their patches face each other) or through
a mirror patch (``Mirror.transfer`` hit test, image-source leg). A path of n bounces is a walk
source -> v_1 -> ... -> v_n -> camera over legs, v_1 the vertex of an illuminated patch and v_n of
an observed one. Each path gets the window of bins its deposit can reach: its delay at the
initial geometry plus the impulse response's support, widened by how far the bounds let its
moving vertices travel; the model's output is the union of windows per trace (the *support*).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..brdf import Mirror

__all__ = ["LegTable", "PathGroup", "legs_between", "enumerate_paths", "windows", "general_triples"]


@dataclass
class LegTable:
    """Legs between vertices: ``src``, ``dst`` (vertex indices) and ``via`` (mirror patch, -1)."""

    src: np.ndarray
    dst: np.ndarray
    via: np.ndarray


@dataclass
class PathGroup:
    """Paths of one bounce order and one mirror signature (``via`` pattern of their legs)."""

    verts: np.ndarray        # (P, n) vertex indices
    via: tuple               # (n - 1,) mirror patch per leg (-1 direct), shared by the group
    trace: np.ndarray        # (P,) flat trace index: row * n_obs + column
    variable: np.ndarray     # (P,) bool: some vertex moves with the unknowns
    k0: np.ndarray | None = None   # (P,) first bin of the window
    k1: np.ndarray | None = None   # (P,) one past the last bin


def legs_between(layout, patch_vis, mirrors: dict, z, n, areas) -> LegTable:
    """All vertex legs: direct ones where the patches see each other, and image-source legs
    through each mirror patch (``mirrors``: patch -> Mirror) where the reflected ray hits it."""
    P = layout.patch
    pv = patch_vis[P][:, P]
    vs, vd = np.nonzero(pv)
    src, dst, via = [vs], [vd], [np.full(len(vs), -1)]
    others = np.flatnonzero(~np.isin(np.arange(len(z)), list(mirrors)))
    for m, mir in mirrors.items():
        hh, kk = np.meshgrid(others, others, indexing="ij")
        hh, kk = hh.ravel(), kk.ravel()
        sel = hh != kk
        hh, kk = hh[sel], kk[sel]
        hit, _, _, hp = Mirror.transfer(z[hh], z[m], n[m], areas[m], z[kk], mir.reflectance)
        u1 = hp - z[hh]
        u2 = z[kk] - hp
        ok = hit & (np.sum(u1 * n[hh], axis=1) > 0) & (np.sum(-u2 * n[kk], axis=1) > 0)
        for h, k in zip(hh[ok], kk[ok]):
            a = np.arange(layout.first[h], layout.first[h] + layout.count[h])
            b = np.arange(layout.first[k], layout.first[k] + layout.count[k])
            aa, bb = np.meshgrid(a, b, indexing="ij")
            src.append(aa.ravel()); dst.append(bb.ravel()); via.append(np.full(aa.size, m))
    return LegTable(np.concatenate(src), np.concatenate(dst), np.concatenate(via))


def enumerate_paths(legs: LegTable, ill_vertex: np.ndarray, obs_col_of_vertex: np.ndarray,
                    n_obs: int, bounces: int, moving: np.ndarray, hidden: np.ndarray | None = None,
                    bounces_hidden: int | None = None) -> list[PathGroup]:
    """Paths of 1..bounces bounces grouped by (bounce order, mirror signature).

    ``ill_vertex[r]`` is the vertex of STIR row r; ``obs_col_of_vertex[v]`` the STIR column
    observing vertex v (-1 if none); ``moving[v]`` whether v's position depends on unknowns;
    paths through a ``hidden`` vertex are kept up to ``bounces_hidden`` bounces only."""
    order = np.argsort(legs.src, kind="stable")
    ls, ld, lv = legs.src[order], legs.dst[order], legs.via[order]
    V = len(obs_col_of_vertex)
    start = np.searchsorted(ls, np.arange(V + 1))
    rows_ = np.arange(len(ill_vertex))
    verts = ill_vertex.reshape(-1, 1)
    vias = np.zeros((len(ill_vertex), 0), int)
    row_of = rows_.copy()
    groups = []
    for nb in range(1, bounces + 1):
        if nb > 1:
            last = verts[:, -1]
            cnt = start[last + 1] - start[last]
            rep = np.repeat(np.arange(len(last)), cnt)
            pos = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt) + start[last][rep]
            verts = np.concatenate([verts[rep], ld[pos][:, None]], axis=1)
            vias = np.concatenate([vias[rep], lv[pos][:, None]], axis=1)
            row_of = row_of[rep]
            if hidden is not None and bounces_hidden is not None and nb > bounces_hidden:
                ok = ~hidden[verts].any(axis=1)
                verts, vias, row_of = verts[ok], vias[ok], row_of[ok]
        col = obs_col_of_vertex[verts[:, -1]]
        keep = col >= 0
        if not keep.any():
            continue
        vk, viak, rk, ck = verts[keep], vias[keep], row_of[keep], col[keep]
        sig, inv = np.unique(viak, axis=0, return_inverse=True) if viak.shape[1] else \
            (np.zeros((1, 0), int), np.zeros(len(vk), int))
        inv = np.asarray(inv).ravel()
        for s in range(len(sig)):
            sel = inv == s
            groups.append(PathGroup(vk[sel], tuple(int(x) for x in sig[s]), rk[sel] * n_obs + ck[sel],
                                    moving[vk[sel]].any(axis=1)))
    return groups


def windows(groups, tau_of, reach: np.ndarray, support_lo: float, support_hi: float, grid,
            n_traces: int):
    """Set each group's windows and return the support: (trace_lo, trace_hi, seg_start, support
    flat indices into stir.reshape(-1), support_trace)."""
    w, t0, nb = grid.bin_width, grid.start, grid.n_bins
    tr_lo = np.full(n_traces, np.iinfo(np.int64).max)
    tr_hi = np.full(n_traces, -1)
    for g in groups:
        tau = tau_of(g)
        slack = 2.0 * reach[g.verts].sum(axis=1)
        g.k0 = np.floor((tau - slack + support_lo - t0) / w).astype(np.int64)
        g.k1 = np.ceil((tau + slack + support_hi - t0) / w).astype(np.int64) + 1
        k0c, k1c = np.clip(g.k0, 0, nb), np.clip(g.k1, 0, nb)
        ok = k1c > k0c
        np.minimum.at(tr_lo, g.trace[ok], k0c[ok])
        np.maximum.at(tr_hi, g.trace[ok], k1c[ok])
    has = tr_hi > tr_lo
    lo = np.where(has, tr_lo, 0)
    hi = np.where(has, tr_hi, 0)
    seg_len = hi - lo
    seg_start = np.concatenate([[0], np.cumsum(seg_len)])
    n_sup = int(seg_start[-1])
    tr = np.repeat(np.arange(n_traces), seg_len)
    kk = np.arange(n_sup) - np.repeat(seg_start[:-1], seg_len) + np.repeat(lo, seg_len)
    return lo, hi, seg_start, tr * nb + kk, tr


def general_triples(paths, vertex_patch, general) -> np.ndarray:
    """The (previous, patch, next) triples at which a general-BRDF patch is visited by ``paths``
    (previous -1: the source; next -2: the camera), sorted: one unknown f_kij each."""
    out = set()
    for g in paths:
        v = vertex_patch[g.verts]
        n = v.shape[1]
        for m in range(n):
            prev = v[:, m - 1] if m > 0 else np.full(len(v), -1)
            nxt = v[:, m + 1] if m < n - 1 else np.full(len(v), -2)
            sel = general[v[:, m]]
            out.update(zip(prev[sel].tolist(), v[sel, m].tolist(), nxt[sel].tolist()))
    return np.array(sorted(out), int).reshape(-1, 3)
