"""Backprojection and filtered backprojection for any relay: confocal, paired or a full STIR.

When to use: non-confocal or irregular scans (general-NLOS pairs, a full STIR with legs, a
non-planar relay) where LCT and f-k do not apply; also a slow but assumption-light reference.

Equation (ellipsoidal backprojection): each voxel V of a grid parallel to the relay plane sums,
over traces p, the measurement at the voxel's path length

    I(V) = sum_p tau_p(leg_p + |L_p - V| + |V - D_p|),

read by linear interpolation between bin centres. Filtered backprojection applies a discrete
Laplacian to I (``bp_filter="laplacian"``, 3-D; ``"laplacian-z"`` along depth only) and keeps
its negative part -lap(I) >= 0 (a bright surface is a local maximum).

Memory: voxels are processed in chunks of ``chunk_bytes`` / (16 bytes x traces), so the working
set stays bounded whatever the volume size; the volume itself is float32 (4 bytes a voxel).
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
    """Lateral axes (x, y) over the relay's extent and depths z over the time window."""
    c, u, v, w = relay.frame
    P = np.vstack([relay.L, relay.D]) - c
    a, b = P @ u, P @ v
    n = int(st.n_lateral) if st.n_lateral is not None else (
        int(round(math.sqrt(relay.n_traces))) if relay.confocal else 32)
    x = np.linspace(a.min(), a.max(), n)
    y = np.linspace(b.min(), b.max(), n)
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
    settings : ``VolumeSettings`` (bin_factor, gate_m, t_max, n_lateral, z_range, n_depth,
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
    c, u, v, wn = relay.frame
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    V = (c[None] + xx.reshape(-1, 1) * u + yy.reshape(-1, 1) * v + zz.reshape(-1, 1) * wn).astype(np.float32)
    nvox, P = len(V), relay.n_traces
    if P == 0:
        raise ReconstructionError("Backprojection needs at least one trace; the relay holds none.")
    flat = np.concatenate([tr, np.zeros((P, 1), np.float32)], axis=1).ravel()
    T1 = tr.shape[1]
    L = relay.L.astype(np.float32)
    D = relay.D.astype(np.float32)
    leg = relay.leg.astype(np.float32)
    base = (np.arange(P) * (T1 + 1)).astype(np.int64)
    chunk = max(1, int(st.chunk_bytes // (16 * P)))
    out = np.zeros(nvox, np.float32)
    k0 = np.float32(g.start / w + 0.5)  # index = (t - start)/w - 0.5 (bin centres)
    for s in range(0, nvox, chunk):
        Vc = V[s:s + chunk]
        t = _dist(Vc, L) + _dist(Vc, D) + leg[None, :]
        pos = t / np.float32(w) - k0
        i0 = np.floor(pos)
        fr = pos - i0
        i0 = i0.astype(np.int64)
        bad = (i0 < 0) | (i0 >= T1 - 1)
        i0[bad] = T1  # the zero column
        idx = i0 + base[None, :]
        val = flat[idx] * (1 - fr) + flat[np.where(bad, idx, idx + 1)] * fr
        out[s:s + chunk] = val.sum(axis=1)
    vol = out.reshape(len(z), len(y), len(x))
    if st.bp_filter == "laplacian":
        vol = np.maximum(-laplace(vol), 0).astype(np.float32)
    elif st.bp_filter == "laplacian-z":
        d2 = np.zeros_like(vol)
        d2[1:-1] = vol[2:] - 2 * vol[1:-1] + vol[:-2]
        vol = np.maximum(-d2, 0).astype(np.float32)
    info = {"bin_width_m": w, "gate_m": gate, "filter": st.bp_filter, "n_traces": P,
            "chunk_voxels": chunk, "wall_time_s": time.perf_counter() - t0,
            "grid": f"{len(x)}x{len(y)} lateral, {len(z)} depths"}
    return Volume(vol, x, y, z, relay.frame, "bp" if st.bp_filter == "none" else "fbp", info)


def _dist(V, P):
    d = (V[:, None, 0] - P[None, :, 0]) ** 2
    d += (V[:, None, 1] - P[None, :, 1]) ** 2
    d += (V[:, None, 2] - P[None, :, 2]) ** 2
    return np.sqrt(d)
