"""The depth-map parameterisation of a hidden surface: nodes on a grid parallel to a plane.

Node (iy, ix) sits at X = c + x[ix] u + y[iy] v + z w (frame (c, u, v, w), w pointing from the
relay into the hidden scene), carries depth z and albedo rho. With the depth gradients
(gx, gy) = (dz/dx, dz/dy) (central differences, second-order one-sided at the border) the element's normal,
facing the relay, and area are

    n = -(w - gx u - gy v) / sqrt(1 + gx^2 + gy^2),     a = hx hy sqrt(1 + gx^2 + gy^2).

Inside its cell the surface is the node's second-order patch
z(dx, dy) = z + gx dx + gy dy + (zxx dx^2 + zyy dy^2) / 2 + zxy dx dy, with the curvatures from
second differences (``curvature_ops``): cells are not flat, so a curved object is not a set of
facets. The discrete Laplacian (5-point, Neumann border) is the smoothness prior's operator.

With ``labels`` (one integer per node) the grid holds separate height fields: every difference
operator runs along each row's and column's runs of equal label only, each run's ends taking the
border's stencils, so a node's depth never enters the gradient, curvature or Laplacian of a node
of another label (two surfaces side by side at different depths: ``steps.py``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["DepthGrid", "normal_std"]


def _diff_1d(n: int, h: float) -> sp.csr_matrix:
    """First differences / h: central inside, second-order one-sided at the border (exact for
    a parabola, like the central ones: the border cells of a curved surface are not tilted)."""
    if n == 1:
        return sp.csr_matrix((1, 1))
    D = sp.lil_matrix((n, n))
    if n == 2:
        D[0, 0], D[0, 1] = -1.0 / h, 1.0 / h
        D[1, 0], D[1, 1] = -1.0 / h, 1.0 / h
        return D.tocsr()
    for i in range(1, n - 1):
        D[i, i - 1], D[i, i + 1] = -0.5 / h, 0.5 / h
    D[0, 0], D[0, 1], D[0, 2] = -1.5 / h, 2.0 / h, -0.5 / h
    D[n - 1, n - 1], D[n - 1, n - 2], D[n - 1, n - 3] = 1.5 / h, -2.0 / h, 0.5 / h
    return D.tocsr()


def _second_1d(n: int, h: float) -> sp.csr_matrix:
    """Second differences / h^2; a border node takes its inner neighbour's stencil."""
    if n < 3:
        return sp.csr_matrix((n, n))
    D = sp.lil_matrix((n, n))
    for i in range(n):
        c = min(max(i, 1), n - 2)
        D[i, c - 1], D[i, c], D[i, c + 1] = 1.0 / h ** 2, -2.0 / h ** 2, 1.0 / h ** 2
    return D.tocsr()


def _runs(labels: np.ndarray, axis: int, op1d) -> sp.csr_matrix:
    """The (n, n) operator applying ``op1d(length)`` to each run of equal label along ``axis``
    (1: along x, inside each row; 0: along y, inside each column) of the (ny, nx) ``labels``."""
    ny, nx = labels.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    lines = [(labels[i], idx[i]) for i in range(ny)] if axis == 1 else [(labels[:, j], idx[:, j]) for j in range(nx)]
    rows, cols, vals = [], [], []
    for lab, ids in lines:
        cut = np.flatnonzero(np.diff(lab) != 0) + 1
        for seg in np.split(ids, cut):
            D = sp.coo_matrix(op1d(len(seg)))
            rows.append(seg[D.row])
            cols.append(seg[D.col])
            vals.append(D.data)
    n = ny * nx
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))


def _lap_1d(n: int) -> sp.csr_matrix:
    if n == 1:
        return sp.csr_matrix((1, 1))
    main = -2.0 * np.ones(n)
    main[0] = main[-1] = -1.0
    return sp.diags([np.ones(n - 1), main, np.ones(n - 1)], [-1, 0, 1]).tocsr()


@dataclass
class DepthGrid:
    """A lateral grid (x columns, y rows) in a frame; node index n = iy * nx + ix; ``labels``
    (n,) integers: separate height fields (the module docstring), or None: one."""

    x: np.ndarray
    y: np.ndarray
    frame: tuple
    labels: np.ndarray | None = None

    def __post_init__(self):
        if self.labels is not None:
            lab = np.asarray(self.labels)
            if lab.shape != (self.n,) or not np.issubdtype(lab.dtype, np.integer):
                from ...errors import ReconstructionError
                raise ReconstructionError(f"DepthGrid labels must be {self.n} integers, one per node (row-major); "
                                          f"got shape {lab.shape} of {lab.dtype}.")

    def _lab(self):
        return None if self.labels is None else np.asarray(self.labels).reshape(self.shape)

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
        lab = self._lab()
        if lab is not None:
            return (_runs(lab, 1, lambda k: _diff_1d(k, self.hx)), _runs(lab, 0, lambda k: _diff_1d(k, self.hy)))
        Gx = sp.kron(sp.eye(ny), _diff_1d(nx, self.hx)).tocsr()
        Gy = sp.kron(_diff_1d(ny, self.hy), sp.eye(nx)).tocsr()
        return Gx, Gy

    def curvature_ops(self) -> tuple[sp.csr_matrix, sp.csr_matrix, sp.csr_matrix]:
        """Sparse (n, n) operators giving zxx, zyy, zxy (second differences; a border node takes
        its inner neighbour's stencil): the curvature of the surface inside each node's cell."""
        ny, nx = self.shape
        lab = self._lab()
        if lab is not None:
            Dxx = _runs(lab, 1, lambda k: _second_1d(k, self.hx))
            Dyy = _runs(lab, 0, lambda k: _second_1d(k, self.hy))
        else:
            Dxx = sp.kron(sp.eye(ny), _second_1d(nx, self.hx)).tocsr()
            Dyy = sp.kron(_second_1d(ny, self.hy), sp.eye(nx)).tocsr()
        Gx, Gy = self.gradient_ops()
        return Dxx, Dyy, (Gy @ Gx).tocsr()

    def laplacian(self) -> sp.csr_matrix:
        """5-point Laplacian (unit spacing, Neumann border): second differences of depth."""
        ny, nx = self.shape
        lab = self._lab()
        if lab is not None:
            return (_runs(lab, 1, _lap_1d) + _runs(lab, 0, _lap_1d)).tocsr()
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


def normal_std(grid: DepthGrid, gx, gy, vxx, vyy, vxy) -> np.ndarray:
    """Std of the unit normal's components from the covariance of the depth gradients."""
    _, u, v, w = grid.frame
    s = np.sqrt(1 + gx ** 2 + gy ** 2)
    a = -(w[None] - gx[:, None] * u[None] - gy[:, None] * v[None])  # unnormalised normal
    # d(a/s)/dgx = u/s - a gx / s^3 ; d(a/s)/dgy = v/s - a gy / s^3
    dx = u[None] / s[:, None] - a * (gx / s ** 3)[:, None]
    dy = v[None] / s[:, None] - a * (gy / s ** 3)[:, None]
    var = dx ** 2 * vxx[:, None] + dy ** 2 * vyy[:, None] + 2 * dx * dy * vxy[:, None]
    return np.sqrt(np.maximum(var, 0))
