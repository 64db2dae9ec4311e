"""Model-light depth of a hidden surface from the rising edges of a rectified confocal scan.

When to use: as an independent check of a surface fit's or a volume's depth on a confocal scan
(t = 0 at the wall): it needs neither a radiometric model (falloff, BRDF), nor a background
model, nor the response's shape, only that the hidden return's response peaks where the wall's
own return does (the convention that puts t = 0 at the direct peak).

Equation: under a surface whose nearest point to scan point p is at distance d_p, the confocal
trace starts as a step at path 2 d_p convolved with the response r: y_p(t) ~ a R(t - 2 d_p) +
(slow terms), so dy_p / dt ~ a r(t - 2 d_p) peaks at t = 2 d_p + (the response's mode), which
is 2 d_p when the mode is at t = 0. Per block of ``block`` x ``block`` scan points: sum their
traces, smooth them along time with a Gaussian of ``smooth_bins`` bins (symmetric: no shift),
take the time derivative, find its largest value after the gate, refine it by a parabola through
the three samples, and read d = t / 2 (bin k covers [start + k w, start + (k + 1) w]). The depth
of the scan is the median over the brightest ``bright`` fraction of blocks (their counts in the
window), where the nearest surface point lies under the block.

Neglects: the surface's own decay of the return after its onset (it moves the derivative's peak
earlier by a small fraction of the response width), a block holding two depths, a response whose
mode differs between the wall's return and the hidden return (which this check exposes: it is
what it measures against the wall's return).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from ..errors import ReconstructionError
from .relay import Relay, confocal_grid

__all__ = ["OnsetDepths", "onset_depths"]


@dataclass
class OnsetDepths:
    """Per-block depths (ny, nx) of the steepest rising edge, the blocks' counts in the window,
    the block centres, the scan's depth (median over the bright blocks) with its 10th / 90th
    percentiles, and the direct (wall) return's peak from t = 0 in metres of path (parabola on
    the summed first bins; None when the traces hold no direct return)."""

    depth: np.ndarray
    strength: np.ndarray
    x: np.ndarray
    y: np.ndarray
    median: float
    p10: float
    p90: float
    direct_peak: float | None


def onset_depths(relay: Relay, gate: float, t_max: float, block: int = 2, smooth_bins: float = 4.0,
                 bright: float = 0.25) -> OnsetDepths:
    """Depths from the steepest rising edge of each block of a confocal ``relay`` (see the
    module docstring), searched on paths in [gate, t_max] (metres)."""
    if not (t_max > gate >= 0):
        raise ReconstructionError(f"onset_depths needs 0 <= gate < t_max; got gate={gate!r}, t_max={t_max!r}.")
    if not (0 < bright <= 1) or int(block) < 1 or not (smooth_bins > 0):
        raise ReconstructionError(f"onset_depths needs block >= 1, smooth_bins > 0 and bright in (0, 1]; "
                                  f"got {block!r}, {smooth_bins!r}, {bright!r}.")
    cg = confocal_grid(relay)
    g = cg.grid
    w = g.bin_width
    k_lo = max(int(math.ceil((gate - g.start) / w)), 1)
    k_hi = min(int(math.floor((t_max - g.start) / w)), g.n_bins - 1)
    if k_hi - k_lo < 8:
        raise ReconstructionError(f"onset_depths: the window [{gate}, {t_max}] m holds fewer than 8 bins.")
    n = (len(cg.x) // block) * block
    d = np.asarray(cg.data[:n, :n, : k_hi + 2], float).copy()
    head = d[..., : min(k_lo, 64)].sum(axis=(0, 1))
    d[..., :k_lo] = 0.0
    m = n // block
    b = d.reshape(m, block, m, block, -1).sum(axis=(1, 3))
    dg = np.gradient(gaussian_filter1d(b, smooth_bins, axis=2), axis=2)[..., k_lo:k_hi]
    k = np.clip(np.argmax(dg, axis=2), 1, k_hi - k_lo - 2)
    ii, jj = np.indices(k.shape)
    a0, a1, a2 = dg[ii, jj, k - 1], dg[ii, jj, k], dg[ii, jj, k + 1]
    den = a0 - 2 * a1 + a2
    off = np.where(den < 0, 0.5 * (a0 - a2) / np.where(den < 0, den, -1.0), 0.0)
    depth = 0.5 * (g.start + (k_lo + k + 0.5 + off) * w)
    strength = b[..., k_lo:k_hi].sum(axis=2)
    sel = strength >= np.quantile(strength, 1.0 - bright)
    direct = None
    if head.size >= 3 and int(np.argmax(head)) == 0 and head[0] > 0:
        c0, c1, c2 = head[:3]
        dd = c0 - 2 * c1 + c2
        v = 1.0 - (c2 - c0) / (2 * dd) if dd < 0 else 0.0     # vertex, in bins from bin 0's index
        direct = float(g.start + (v + 0.5) * w)
    xs = cg.x[:n].reshape(m, block).mean(axis=1)
    ys = cg.y[:n].reshape(m, block).mean(axis=1)
    z = depth[sel]
    return OnsetDepths(depth, strength, xs, ys, float(np.median(z)), float(np.percentile(z, 10)),
                       float(np.percentile(z, 90)), direct)
