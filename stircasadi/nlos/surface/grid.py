"""The depth-map parameterisation of a hidden surface: nodes on a grid parallel to a plane.

Node (iy, ix) sits at X = c + x[ix] u + y[iy] v + z w (frame (c, u, v, w), w pointing from the
relay into the hidden scene), carries depth z and albedo rho. With the depth gradients
(gx, gy) = (dz/dx, dz/dy) (central differences, one-sided at the border) the element's normal,
facing the relay, and area are

    n = -(w - gx u - gy v) / sqrt(1 + gx^2 + gy^2),     a = hx hy sqrt(1 + gx^2 + gy^2).

The discrete Laplacian (5-point, Neumann border) is the smoothness prior's operator.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["DepthGrid"]


def _diff_1d(n: int, h: float) -> sp.csr_matrix:
    if n == 1:
        return sp.csr_matrix((1, 1))
    D = sp.lil_matrix((n, n))
    for i in range(n):
        if i == 0:
            D[i, 0], D[i, 1] = -1.0 / h, 1.0 / h
        elif i == n - 1:
            D[i, n - 2], D[i, n - 1] = -1.0 / h, 1.0 / h
        else:
            D[i, i - 1], D[i, i + 1] = -0.5 / h, 0.5 / h
    return D.tocsr()


def _lap_1d(n: int) -> sp.csr_matrix:
    if n == 1:
        return sp.csr_matrix((1, 1))
    main = -2.0 * np.ones(n)
    main[0] = main[-1] = -1.0
    return sp.diags([np.ones(n - 1), main, np.ones(n - 1)], [-1, 0, 1]).tocsr()


@dataclass
class DepthGrid:
    """A lateral grid (x columns, y rows) in a frame; node index n = iy * nx + ix."""

    x: np.ndarray
    y: np.ndarray
    frame: tuple

    @property
    def shape(self) -> tuple[int, int]:
        return len(self.y), len(self.x)

    @property
    def n(self) -> int:
        return len(self.x) * len(self.y)

    @property
    def hx(self) -> float:
        return float(self.x[1] - self.x[0]) if len(self.x) > 1 else 1.0

    @property
    def hy(self) -> float:
        return float(self.y[1] - self.y[0]) if len(self.y) > 1 else 1.0

    def base_points(self) -> np.ndarray:
        """(n, 3) node positions at zero depth."""
        c, u, v, _ = self.frame
        yy, xx = np.meshgrid(self.y, self.x, indexing="ij")
        return c[None] + xx.reshape(-1, 1) * u[None] + yy.reshape(-1, 1) * v[None]

    def gradient_ops(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """Sparse (n, n) operators giving gx, gy from the flattened depth map."""
        ny, nx = self.shape
        Gx = sp.kron(sp.eye(ny), _diff_1d(nx, self.hx)).tocsr()
        Gy = sp.kron(_diff_1d(ny, self.hy), sp.eye(nx)).tocsr()
        return Gx, Gy

    def laplacian(self) -> sp.csr_matrix:
        """5-point Laplacian (unit spacing, Neumann border): second differences of depth."""
        ny, nx = self.shape
        return (sp.kron(sp.eye(ny), _lap_1d(nx)) + sp.kron(_lap_1d(ny), sp.eye(nx))).tocsr()

    def geometry(self, z: np.ndarray):
        """Positions (n, 3), unit normals facing the relay (n, 3), areas (n,) for depths z."""
        c, u, v, w = self.frame
        Gx, Gy = self.gradient_ops()
        gx, gy = Gx @ z, Gy @ z
        s = np.sqrt(1 + gx ** 2 + gy ** 2)
        X = self.base_points() + z[:, None] * w[None]
        nrm = -(w[None] - gx[:, None] * u[None] - gy[:, None] * v[None]) / s[:, None]
        return X, nrm, self.hx * self.hy * s

    def resample(self, values: np.ndarray, other: "DepthGrid") -> np.ndarray:
        """Values on this grid's nodes, bilinearly interpolated at ``other``'s nodes."""
        from scipy.interpolate import RegularGridInterpolator

        f = RegularGridInterpolator((self.y, self.x), np.asarray(values).reshape(self.shape),
                                    bounds_error=False, fill_value=None)
        yy, xx = np.meshgrid(other.y, other.x, indexing="ij")
        return f(np.stack([yy.ravel(), xx.ravel()], axis=1))

    @classmethod
    def square(cls, frame, x_range, y_range, nx: int, ny: int | None = None) -> "DepthGrid":
        return cls(np.linspace(*x_range, nx), np.linspace(*y_range, ny or nx), frame)
