"""Bounce expansion: the STIR as an exact sum over every light path of up to K bounces.

When to use: the reference answer for small K (first/second/third bounce geometry), any sensor
(ideal box binning included), exact or integer delays. Cost grows as M^K paths (it enumerates
them, per illuminated patch), so K <= 3 for hundreds of patches.

Equation: for walks source -> u_1 -> ... -> u_n -> camera on the delay network of
``stircasadi.transport.system`` (n = 1..K), amplitude = product of the term coefficients and
arrival tau = sum of the term lengths; each path is deposited at its exact tau through the
impulse response. Nothing is neglected beyond the network itself and the K truncation, whose
omitted energy is reported (``omitted_energy_rel``) by ``stircasadi.transport.simulate``.
"""
from __future__ import annotations

import numpy as np

from ..progress import progress
from ..timegrid import TimeGrid
from .deposit import deposit
from .system import TransportSystem


def _by_col(terms, n_cols):
    r, c, v, l = terms
    order = np.argsort(c, kind="stable")
    indptr = np.zeros(n_cols + 1, np.int64)
    np.add.at(indptr, c + 1, 1)
    return np.cumsum(indptr), r[order], v[order], l[order]


def _expand(nodes, amp, tau, csr):
    indptr, rows, vals, lens = csr
    starts = indptr[nodes]
    counts = indptr[nodes + 1] - starts
    total = int(counts.sum())
    if total == 0:
        z = np.zeros(0)
        return np.zeros(0, np.int64), z, z
    rep = np.repeat(np.arange(len(nodes)), counts)
    pos = np.arange(total) - np.repeat(np.cumsum(counts) - counts, counts) + starts[rep]
    return rows[pos], amp[rep] * vals[pos], tau[rep] + lens[pos]


def path_sum(system: TransportSystem, grid: TimeGrid, irf, bounces: int,
             per_bounce: bool = False, max_frontier: int = 4_000_000):
    """STIR (n_ill, n_obs, n_bins) summed over paths with 1..bounces bounces.

    With ``per_bounce`` also returns a list of the per-bounce STIRs (index 0 = first bounce).
    """
    integer = system.delay_mode == "integer"
    n_ill, n_obs, nb = system.n_ill, system.n_obs, grid.n_bins
    S = _by_col(system.S, n_ill)
    T = _by_col(system.T, system.n_nodes)
    O = _by_col(system.O, system.n_nodes)
    stir = np.zeros((n_ill, n_obs, nb))
    parts = [np.zeros((n_ill, n_obs, nb)) for _ in range(bounces)] if per_bounce else None
    for p in progress(range(n_ill), desc="path sums", unit="pulse"):
        nodes, amp, tau = _expand(np.array([p]), np.ones(1), np.zeros(1), S)
        for n in range(1, bounces + 1):
            if len(nodes) == 0:
                break
            _deposit_level(stir[p], parts[n - 1][p] if per_bounce else None, nodes, amp, tau, O,
                           grid, irf, integer, max_frontier)
            if n < bounces:
                nodes, amp, tau = _expand_chunked(nodes, amp, tau, T, max_frontier)
    return (stir, parts) if per_bounce else stir


def _deposit_level(out, part, nodes, amp, tau, O, grid, irf, integer, chunk):
    for s in range(0, len(nodes), chunk):
        j, a, t = _expand(nodes[s:s + chunk], amp[s:s + chunk], tau[s:s + chunk], O)
        if len(j):
            deposit(out, j, a, t, grid, irf, integer)
            if part is not None:
                deposit(part, j, a, t, grid, irf, integer)


def _expand_chunked(nodes, amp, tau, T, chunk):
    outs = [_expand(nodes[s:s + chunk], amp[s:s + chunk], tau[s:s + chunk], T)
            for s in range(0, len(nodes), chunk)]
    return (np.concatenate([o[0] for o in outs]), np.concatenate([o[1] for o in outs]),
            np.concatenate([o[2] for o in outs]))
