"""A reconstructed volume on a stated grid, and the depth and albedo maps read from it.

When to use: every volumetric method (``lct``, ``fk``, ``backprojection``) returns a
:class:`Volume`; :meth:`Volume.maps` reads, per lateral column, the depth of the brightest voxel
(refined below a voxel by a parabola through its neighbours), its value (the albedo-like
intensity, normalised to the brightest column) and a mask of columns that stand out of the
volume's background (median + ``k_mad`` MADs of the column maxima).

Grid: ``vol[iz, iy, ix]`` at points ``centre + x[ix] u + y[iy] v + z[iz] w`` of the relay frame
(w into the hidden scene). Neglects: a column holding two surfaces keeps only the brightest.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Volume", "Maps", "plane_fit"]


@dataclass
class Maps:
    """Per-column readings of a volume: ``depth`` (m along w), ``albedo`` (relative, max 1),
    ``mask`` (column holds a surface), on the lateral grid ``x`` (columns) by ``y`` (rows)."""

    depth: np.ndarray
    albedo: np.ndarray
    mask: np.ndarray
    x: np.ndarray
    y: np.ndarray
    frame: tuple

    def points(self) -> np.ndarray:
        """(ny, nx, 3) positions of the depth map in the capture's frame."""
        c, u, v, w = self.frame
        yy, xx = np.meshgrid(self.y, self.x, indexing="ij")
        return (c[None, None] + xx[..., None] * u + yy[..., None] * v
                + self.depth[..., None] * w)


@dataclass
class Volume:
    """``vol[iz, iy, ix]`` (float32) over the axes ``z``, ``y``, ``x`` of ``frame`` (see module)."""

    vol: np.ndarray
    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    frame: tuple
    method: str
    info: dict = field(default_factory=dict)

    def maps(self, k_mad: float = 6.0, z_min: float | None = None) -> Maps:
        """Depth / albedo / mask maps (see the module docstring). ``z_min`` ignores shallower voxels."""
        v = np.asarray(self.vol, float)
        z = self.z
        if z_min is not None:
            v = v.copy()
            v[z < z_min] = 0.0
        k = np.argmax(v, axis=0)
        ny, nx = k.shape
        iy, ix = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
        peak = v[k, iy, ix]
        km = np.clip(k - 1, 0, len(z) - 1)
        kp = np.clip(k + 1, 0, len(z) - 1)
        a, b = v[km, iy, ix], v[kp, iy, ix]
        den = a - 2 * peak + b
        off = np.where((den < 0) & (k > 0) & (k < len(z) - 1), 0.5 * (a - b) / np.where(den < 0, den, -1), 0.0)
        dz = (z[-1] - z[0]) / max(len(z) - 1, 1)
        depth = z[k] + np.clip(off, -0.5, 0.5) * dz
        top = float(peak.max()) if peak.size else 0.0
        albedo = peak / top if top > 0 else np.zeros_like(peak)
        med = float(np.median(peak))
        mad = float(np.median(np.abs(peak - med))) * 1.4826
        mask = peak > med + k_mad * max(mad, 1e-12 * max(top, 1e-300))
        if not mask.any() and top > 0:
            mask = peak >= 0.5 * top
        return Maps(depth, albedo, mask, self.x, self.y, self.frame)

    def nbytes(self) -> int:
        return int(self.vol.nbytes)


def plane_fit(points, weights) -> tuple[float, float]:
    """Weighted plane through reconstructed points (``points`` (N, 3) in the scan's frame, z the
    wall's normal axis; ``weights`` (N,) >= 0, e.g. albedo), with the points beyond 3 MADs of the
    plane dropped twice. Returns the plane's depth where it crosses the scan's axis (x = y = 0),
    metres, and its tilt from the wall normal, degrees."""
    P = np.asarray(points, float)
    w = np.asarray(weights, float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 3 or w.shape != (len(P),):
        raise ValueError(f"plane_fit needs points (N >= 3, 3) and weights (N,); got {P.shape} and {w.shape}.")
    for _ in range(3):
        c = np.average(P, axis=0, weights=w)
        n = np.linalg.svd((P - c) * np.sqrt(w)[:, None], full_matrices=False)[2][-1]
        n = n if n[2] < 0 else -n
        d = (P - c) @ n
        keep = np.abs(d - np.median(d)) < 3 * (1.4826 * np.median(np.abs(d - np.median(d))) + 1e-4)
        P, w = P[keep], w[keep]
    return float(c[2] + (n[0] * c[0] + n[1] * c[1]) / n[2]), float(np.degrees(np.arccos(min(1.0, -n[2]))))

