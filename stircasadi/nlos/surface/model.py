"""The differentiable forward model of a depth-map surface seen through a relay.

When to use: built by ``fit.fit_surface`` for one grid level; describes, never solves.

Model of trace p, bin k (left edge t_k, width w):

    m_pk = b + sum_n A(L_p, D_p, X_n, n_n, a_n, rho_n) B(t_k - tau_pn; sigma)

with A, tau, B from ``physics.py`` and (X_n, n_n, a_n) from the depth map (``grid.py``). Each
(trace, node) pair deposits into a window of ``n_win`` bins starting at ``k0[p, n]`` (fixed
for the level, centred on the pair's delay at the level's start; the solver keeps depths and
sigma within bounds that keep the deposit inside it). One CasADi SX Function of a single
pair, with its exact Jacobian with respect to (z, gx, gy, rho, sigma), is mapped over all
pairs; the chain rule through the gradient operators gives derivatives per node.

Memory is bounded by working through ``chunk`` traces at a time.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ...timegrid import TimeGrid
from ..relay import Relay
from .grid import DepthGrid
from .physics import cell_spread, deposit_window, relay_amplitude, relay_delay

__all__ = ["SurfaceModel"]


class SurfaceModel:
    """Forward model and derivatives of one level (grid, relay window, deposit windows)."""

    def __init__(self, grid: DepthGrid, relay: Relay, z_ref: np.ndarray, sigma_max: float,
                 z_slack: float, chunk_pairs: int = 200_000):
        self.grid = grid
        self.relay = relay
        g: TimeGrid = relay.grid
        self.w = g.bin_width
        self.T = g.n_bins
        self.P = relay.n_traces
        self.N = grid.n
        self.Gx, self.Gy = grid.gradient_ops()
        # window: the IRF, the cell's own delay spread (at most 2 sides x 2 / sqrt(12)), slack
        cell = 2.0 * max(grid.hx, grid.hy) / math.sqrt(3.0)
        self.half = 4.5 * math.sqrt(sigma_max ** 2 + cell ** 2) + (2.0 * z_slack + self.w)
        self.n_win = int(math.ceil(2 * self.half / self.w)) + 1
        self.base = grid.base_points()
        self.chunk = max(1, int(chunk_pairs // max(self.N, 1)))
        self.recentre(z_ref)
        self._build()

    def recentre(self, z_ref) -> None:
        """Place every pair's deposit window around its delay for depths ``z_ref``."""
        r, g = self.relay, self.relay.grid
        X, _, _ = self.grid.geometry(np.asarray(z_ref, float))
        tau = relay_delay(r.L[:, None, :], r.D[:, None, :], X[None, :, :], r.leg[:, None])
        self.k0 = np.floor((tau - self.half - g.start) / self.w).astype(np.int64)   # (P, N)

    # ------------------------------------------------------------------ CasADi pair function
    def _build(self):
        c, u, v, wv = (ca.DM(np.asarray(a, float)) for a in self.grid.frame)
        p = ca.SX.sym("p", 5)          # z, gx, gy, rho, sigma
        q = ca.SX.sym("q", 18)         # Xb(3) L(3) D(3) nL(3) nD(3) leg gain t_left
        z, gx, gy, rho, sig = (p[i] for i in range(5))
        s = ca.sqrt(1 + gx ** 2 + gy ** 2)
        X = q[0:3] + z * wv
        nX = -(wv - gx * u - gy * v) / s
        area = self.grid.hx * self.grid.hy * s
        amp = relay_amplitude(q[3:6], q[6:9], q[9:12], q[12:15], X, nX, area, rho, q[16])
        tau = relay_delay(q[3:6], q[6:9], X, q[15])
        left = q[17] + ca.DM(np.arange(self.n_win) * self.w)
        spread = cell_spread(q[3:6], q[6:9], X, u + gx * wv, v + gy * wv, self.grid.hx, self.grid.hy)
        y = deposit_window(amp, tau, left, self.w, ca.sqrt(sig ** 2 + spread ** 2))
        self.f_val = ca.Function("pair", [p, q], [y])
        self.f_jac = ca.Function("pair_jac", [p, q], [y, ca.jacobian(y, p)])

    # ------------------------------------------------------------------ numeric evaluation
    def _pairs(self, t0: int, t1: int, z, gx, gy, rho, sigma):
        """Parameter (5, K) and constant (18, K) columns of the pairs of traces t0..t1."""
        r = self.relay
        nt = t1 - t0
        K = nt * self.N
        P = np.empty((5, K))
        P[0] = np.tile(z, nt)
        P[1] = np.tile(gx, nt)
        P[2] = np.tile(gy, nt)
        P[3] = np.tile(rho, nt)
        P[4] = sigma
        Q = np.empty((18, K))
        Q[0:3] = np.tile(self.base.T, nt)
        for a, arr in ((3, r.L), (6, r.D), (9, r.nL), (12, r.nD)):
            Q[a:a + 3] = np.repeat(arr[t0:t1].T, self.N, axis=1)
        Q[15] = np.repeat(r.leg[t0:t1], self.N)
        Q[16] = np.repeat(r.gain[t0:t1], self.N)
        k0 = self.k0[t0:t1].ravel()
        Q[17] = r.grid.start + k0 * self.w
        return P, Q, k0

    def _index(self, t0, t1, k0):
        """Flat (trace, bin) index of every window bin (K, n_win) and its validity."""
        kk = k0[:, None] + np.arange(self.n_win)[None, :]
        ok = (kk >= 0) & (kk < self.T)
        tr = np.repeat(np.arange(t0, t1), self.N)[:, None]
        return np.where(ok, tr * self.T + kk, 0), ok

    def predict(self, z, rho, sigma, bg) -> np.ndarray:
        """Model traces (P, T)."""
        gx, gy = self.Gx @ z, self.Gy @ z
        out = np.full(self.P * self.T, float(bg))
        for t0 in range(0, self.P, self.chunk):
            t1 = min(t0 + self.chunk, self.P)
            P, Q, k0 = self._pairs(t0, t1, z, gx, gy, rho, sigma)
            Y = np.asarray(self.f_val.map(P.shape[1])(P, Q)).T          # (K, n_win)
            idx, ok = self._index(t0, t1, k0)
            out += np.bincount(idx[ok], Y[ok], minlength=out.size)
        return out.reshape(self.P, self.T)

    def _local(self, t0, t1, z, gx, gy, rho, sigma):
        P, Q, k0 = self._pairs(t0, t1, z, gx, gy, rho, sigma)
        K = P.shape[1]
        Y, J = self.f_jac.map(K)(P, Q)
        Y = np.asarray(Y).T                                             # (K, n_win)
        J = np.asarray(J).reshape(self.n_win, K, 5).transpose(1, 0, 2)  # (K, n_win, 5)
        idx, ok = self._index(t0, t1, k0)
        return Y, J, idx, ok

    def value_and_grad(self, z, rho, sigma, bg, e: np.ndarray | None = None, y=None, wgt=None):
        """Model (P, T) and, given the weighted residual derivative e = dF/dm (P, T), the
        gradient of F with respect to (z, rho, sigma, bg). With e None, e is computed from the
        data y and weights wgt (F = 1/2 sum wgt (m - y)^2) after the model."""
        gx, gy = self.Gx @ z, self.Gy @ z
        m = np.full(self.P * self.T, float(bg))
        parts = []
        for t0 in range(0, self.P, self.chunk):
            t1 = min(t0 + self.chunk, self.P)
            Y, J, idx, ok = self._local(t0, t1, z, gx, gy, rho, sigma)
            m += np.bincount(idx[ok], Y[ok], minlength=m.size)
            parts.append((J, idx, ok))
        m = m.reshape(self.P, self.T)
        if e is None:
            e = wgt * (m - y)
        ef = e.ravel()
        gl = np.zeros((self.N, 5))
        for J, idx, ok in parts:
            ew = np.where(ok, ef[idx], 0.0)                               # (K, n_win)
            gk = np.einsum("kw,kwj->kj", ew, J)                           # (K, 5)
            gl += gk.reshape(-1, self.N, 5).sum(axis=0)
        gz = gl[:, 0] + self.Gx.T @ gl[:, 1] + self.Gy.T @ gl[:, 2]
        return m, e, (gz, gl[:, 3], float(gl[:, 4].sum()), float(ef.sum()))

    def gauss_newton(self, z, rho, sigma, wgt: np.ndarray, fit_sigma: bool = True):
        """J^T W J over (z, rho[, sigma], bg), built by chunks of traces (dense, n_par^2)."""
        gx, gy = self.Gx @ z, self.Gy @ z
        N = self.N
        npar = 2 * N + (1 if fit_sigma else 0) + 1
        H = np.zeros((npar, npar))
        sw = np.sqrt(wgt).ravel()
        GxT, GyT = self.Gx.T.tocsr(), self.Gy.T.tocsr()
        for t0 in range(0, self.P, self.chunk):
            t1 = min(t0 + self.chunk, self.P)
            _, J, idx, ok = self._local(t0, t1, z, gx, gy, rho, sigma)
            rows_used = np.unique(idx[ok])
            rmap = np.full(self.P * self.T, -1)
            rmap[rows_used] = np.arange(len(rows_used))
            R = len(rows_used)
            node = np.tile(np.arange(N), t1 - t0)[:, None] * np.ones((1, self.n_win), int)
            rr = rmap[idx[ok]]
            nn = node[ok]
            Jok = J[ok] * sw[idx[ok]][:, None]
            Jl = np.zeros(R * 4 * N)
            for j in range(4):
                Jl += np.bincount(rr * (4 * N) + nn + j * N, Jok[:, j], minlength=R * 4 * N)
            Jl = Jl.reshape(R, 4 * N)
            Jz = Jl[:, :N] + (GxT @ Jl[:, N:2 * N].T).T + (GyT @ Jl[:, 2 * N:3 * N].T).T
            cols = [Jz, Jl[:, 3 * N:]]
            if fit_sigma:
                cols.append(np.bincount(rr, Jok[:, 4], minlength=R)[:, None])
            cols.append(sw[rows_used][:, None])
            Jc = np.hstack(cols)
            H += Jc.T @ Jc
        H[-1, -1] = float(np.sum(wgt))   # the background touches every bin, modelled or not
        return H
