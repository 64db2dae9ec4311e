"""Preparing a confocal scan for the wave/cone transforms (LCT and f-k): one place for both.

Steps: arrange the traces on the wall grid (``relay.confocal_grid``), put t = 0 at the wall
(prepend or drop bins so the first bin starts at path 0), sum ``bin_factor`` bins, cut at
``t_max`` and zero bins before the gate (the wall's own return). The gate, when not given, is
past the summed histogram's early peak and its decay to within twice the late background.
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ReconstructionError
from .relay import ConfocalGrid, Relay, confocal_grid
from .settings import VolumeSettings

__all__ = ["prepare", "auto_gate"]


def auto_gate(traces: np.ndarray, centres: np.ndarray) -> float:
    """Path length (m) past the wall's own return in the summed histogram."""
    s = np.asarray(traces, float).reshape(-1, traces.shape[-1]).sum(axis=0)
    head = max(len(s) // 3, 1)
    k_peak = int(np.argmax(s[:head]))
    late = float(np.median(s[len(s) // 2:]))
    after = np.flatnonzero(s[k_peak:] < 2.0 * late + 5 * math.sqrt(max(late, 1.0)))
    k_gate = k_peak + (int(after[0]) if after.size else 0) + 2
    return float(centres[min(k_gate, len(centres) - 1)])


def prepare(relay: Relay, st: VolumeSettings) -> tuple[np.ndarray, ConfocalGrid, float, float]:
    """(data[iy, ix, k] with t = 0 at bin 0's left edge, grid, bin width, gate used)."""
    cg = confocal_grid(relay)
    g = cg.grid
    w = g.bin_width
    shift = g.start / w
    if abs(shift - round(shift)) > 1e-6:
        raise ReconstructionError(f"The time grid must start on a whole bin from t = 0 (start "
                                  f"{g.start:.6g} m, bin {w:.6g} m); resample it first.")
    shift = int(round(shift))
    data = cg.data
    if shift > 0:
        data = np.concatenate([np.zeros(data.shape[:2] + (shift,), data.dtype), data], axis=2)
    elif shift < 0:
        data = data[:, :, -shift:]
    if data.shape[2] < 4:
        raise ReconstructionError("The confocal record holds fewer than 4 bins after t = 0.")
    if st.t_max is not None:
        data = data[:, :, : max(int(math.ceil(st.t_max / w)), 4)]
    f = st.bin_factor
    if f > 1:
        m = (data.shape[2] // f) * f
        data = data[:, :, :m].reshape(data.shape[0], data.shape[1], m // f, f).sum(axis=3)
        w = w * f
    data = np.asarray(data, dtype=st.dtype)
    centres = (np.arange(data.shape[2]) + 0.5) * w
    gate = st.gate_m if st.gate_m is not None else auto_gate(data, centres)
    data[:, :, centres < gate] = 0.0
    return data, cg, w, float(gate)
