"""Backprojection and filtered backprojection for any relay: confocal, paired or a full STIR.

When to use: non-confocal or irregular scans (general-NLOS pairs, a full STIR with legs, a
non-planar relay) where LCT and f-k do not apply; also a slow but assumption-light reference.

Equation (ellipsoidal backprojection): each voxel V of a grid parallel to the relay plane sums,
over traces p, the measurement at the voxel's path length

    I(V) = sum_p tau_p(leg_p + |L_p - V| + |V - D_p|),

read by linear interpolation between bin centres. Filtered backprojection applies a discrete
Laplacian to I (``bp_filter="laplacian"``, 3-D; ``"laplacian-z"`` along depth only) and keeps
its negative part -lap(I) >= 0 (a bright surface is a local maximum).

Vectorised per chunk of traces over the whole volume (float32): the path lengths follow from
separable squared distances in the relay frame, (x - a)^2 + (y - b)^2 + (z - h)^2 broadcast over
the grid's axes, then two gathers and a linear interpolation per voxel and trace. Memory: traces
are processed in chunks of ``chunk_bytes`` / (40 bytes x voxels), so the working set stays
bounded whatever the number of traces; the volume itself is float32 (4 bytes a voxel).
Neglects: the 1/r^2 falloffs and the cosines (no radiometric weighting, as y-tal's bp), the
sensor's impulse response, occlusion.
"""
from __future__ import annotations

import math
import time

import numpy as np
from scipy.ndimage import laplace

from ..errors import ReconstructionError
from .confocal import auto_gate
from .relay import Relay
from .settings import VolumeSettings
from .volume import Volume

__all__ = ["backprojection", "default_grid"]


def default_grid(relay: Relay, st: VolumeSettings, gate: float):
    """Lateral axes (x, y) over the relay's extent (or ``xy_range``) and depths z over the time window."""
    c, u, v, w = relay.frame
    P = np.vstack([relay.L, relay.D]) - c
    a, b = P @ u, P @ v
    n = int(st.n_lateral) if st.n_lateral is not None else (
        int(round(math.sqrt(relay.n_traces))) if relay.confocal else 32)
    x0, x1, y0, y1 = st.xy_range if st.xy_range is not None else (a.min(), a.max(), b.min(), b.max())
    x = np.linspace(x0, x1, n)
    y = np.linspace(y0, y1, n)
    g = relay.grid
    if st.z_range is not None:
        z0, z1 = st.z_range
    else:
        t_hi = g.end if st.t_max is None else min(g.end, st.t_max)
        z0 = max(0.5 * (gate - float(np.max(relay.leg))), 0.0)
        z1 = max(0.5 * (t_hi - float(np.min(relay.leg))), z0 + g.bin_width)
    nz = st.n_depth if st.n_depth is not None else max(int(math.ceil((z1 - z0) / (g.bin_width / 2))), 2)
    z = np.linspace(z0, z1, int(nz))
    return x, y, z


def backprojection(relay: Relay, settings: VolumeSettings | None = None) -> Volume:
    """Backproject (and filter) a relay's traces onto a voxel grid parallel to the relay plane.

    Parameters
    ----------
    relay : any ``Relay`` (confocal, paired or from a full STIR).
    settings : ``VolumeSettings`` (bin_factor, gate_m, t_max, n_lateral, xy_range, z_range, n_depth,
        bp_filter, chunk_bytes).

    Returns
    -------
    Volume over the grid of :func:`default_grid` (or the one the settings give).
    """
    st = (settings or VolumeSettings(bin_factor=1)).validate()
    t0 = time.perf_counter()
    g = relay.grid
    tr = relay.traces
    w = g.bin_width
    if st.bin_factor > 1:
        f = st.bin_factor
        m = (tr.shape[1] // f) * f
        tr = tr[:, :m].reshape(tr.shape[0], m // f, f).sum(axis=2)
        w = w * f
    centres = g.start + (np.arange(tr.shape[1]) + 0.5) * w
    gate = st.gate_m if st.gate_m is not None else auto_gate(tr, centres - relay.leg.mean())
    tr = np.array(tr, dtype=np.float32)
    tr[(centres[None, :] - relay.leg[:, None]) < gate] = 0.0
    if st.t_max is not None:
        tr[:, centres > st.t_max] = 0.0
    x, y, z = default_grid(relay, st, gate)
    P = relay.n_traces
    if P == 0:
        raise ReconstructionError("Backprojection needs at least one trace; the relay holds none.")
    nvox = len(x) * len(y) * len(z)
    T1 = tr.shape[1]
    flat = np.concatenate([tr, np.zeros((P, 1), np.float32)], axis=1)
    # each trace's path length over the whole volume, traces in chunks (work ~ 6 arrays of
    # chunk x voxels): |V - L|^2 = (x - a_L)^2 + (y - b_L)^2 + (z - h_L)^2 in the frame
    c, u, v, wn = relay.frame
    coords = {}
    for name, Q in (("L", relay.L), ("D", relay.D)):
        R = Q - c
        coords[name] = (R @ u, R @ v, R @ wn)
    chunk = max(1, int(st.chunk_bytes // (40 * nvox)))
    out = np.zeros((len(z), len(y), len(x)), np.float32)
    x32, y32, z32 = (np.asarray(a, np.float32) for a in (x, y, z))
    k0 = np.float32(g.start / w + 0.5)  # index = (t - start)/w - 0.5 (bin centres)
    for s0 in range(0, P, chunk):
        sl = slice(s0, min(s0 + chunk, P))
        t = relay.leg[sl].astype(np.float32)[:, None, None, None]
        for name in ("L", "D"):
            a, b, h = (np.asarray(q[sl], np.float32) for q in coords[name])
            d2 = ((z32[None, :] - h[:, None]) ** 2)[:, :, None, None] \
                + ((y32[None, :] - b[:, None]) ** 2)[:, None, :, None] \
                + ((x32[None, :] - a[:, None]) ** 2)[:, None, None, :]
            t = t + np.sqrt(d2)
        pos = t / np.float32(w) - k0
        del t
        i0 = np.floor(pos)
        fr = pos - i0
        del pos
        i0 = i0.astype(np.int64)
        bad = (i0 < 0) | (i0 >= T1 - 1)
        i0[bad] = T1  # the zero column
        i0 += ((np.arange(sl.start, sl.stop) - s0) * (T1 + 1))[:, None, None, None]
        blk = flat[sl].ravel()
        lo = np.take(blk, i0)
        i0[~bad] += 1
        hi = np.take(blk, i0)
        out += np.sum(lo + (hi - lo) * fr, axis=0)
    vol = out
    if st.bp_filter == "laplacian":
        vol = np.maximum(-laplace(vol), 0).astype(np.float32)
    elif st.bp_filter == "laplacian-z":
        d2 = np.zeros_like(vol)
        d2[1:-1] = vol[2:] - 2 * vol[1:-1] + vol[:-2]
        vol = np.maximum(-d2, 0).astype(np.float32)
    info = {"bin_width_m": w, "gate_m": gate, "filter": st.bp_filter, "n_traces": P,
            "chunk_traces": chunk, "wall_time_s": time.perf_counter() - t0,
            "grid": f"{len(x)}x{len(y)} lateral, {len(z)} depths"}
    return Volume(vol, x, y, z, relay.frame, "bp" if st.bp_filter == "none" else "fbp", info)
