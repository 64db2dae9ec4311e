"""The differentiable forward model of a depth-map surface seen through a relay.

When to use: built by ``fit.fit_surface`` for one grid level; describes, never solves. The
solvers read ``predict`` (the model), ``linearise`` (the Gauss-Newton matrix and gradient of
the whitened least squares) and the parameter packing; nothing else.

Model of trace p, bin k (left edge t_k, width w):

    m_pk = b_pk + Phi[ sum_n rho_n A_pn B(t_k - tau_pn; s_pn) ]_k,   s_pn^2 = sigma^2 + c_pn^2,

with the amplitude A (at unit albedo), delay tau and cell variance c^2 (plus the trace's
footprint variance where a trace sums several scan points) from ``physics.py`` at the
node's position and normal (``grid.py``: each node's cell is the second-order patch of its
depth, gradients gx = Gx z, gy = Gy z and curvatures zxx, zyy, zxy from second differences), B the bin integral of the response's core and Phi its slow tails applied along each
trace (``response.py``; the core's width and tail and the slow tails' weights are global
unknowns). The background is b_pk = b0 + b1 q_p exp(-(t_k - t_0) / tau_b): a level plus, when
the relay's own (direct) return q_p is given, that return's slow decay (b1 and tau_b fitted).

Structure used for speed (the brief of issue 13: "profile first"). Every (trace, node) pair
needs only three geometric numbers (A, tau, c^2) and their derivatives with respect to the
node's patch (z, gx, gy, zxx, zyy, zxy): one small CasADi SX function, mapped over the pairs
(and cell sub-samples) of a chunk of traces, compiled by CasADi's JIT where a compiler works
and called through its buffer (NumPy arrays in and out, no DM conversion).
The response then fills a window of bins per pair in NumPy (its value and derivatives come from
F, f and f' at the window's bin edges), and the chunk's Jacobian rows are assembled densely
over (z, rho, globals); the chain rule through the sparse difference operators is one sparse
product (window bins x local unknowns, times the stacked operators), and the slow tails run
along the Jacobian's time axis as one recursion for all tails. The
Gauss-Newton matrix is a sum of per-chunk products J^T W J (BLAS; float32 for the solver's
steps, float64 for the Fisher covariance); without slow tails, rows that no pair reaches only
carry the background; with them, Phi is applied to the chunk's columns along time.
Memory is bounded by ``chunk_bytes`` whatever the number of traces (a prediction's chunks by
``PREDICT_CHUNK_BYTES`` too). A node of albedo zero (LM holds 25-65 % of the 32 x 32 chart's
nodes at that bound) deposits nothing, and every derivative of its bins but the albedo's carries
the albedo as a factor: its bins get bin integrals only, and the depth columns that no lit node's
stencil reaches are left out of the Gram products (``gram.py``), exact zeros either way.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np
import scipy.sparse as sp

from ...errors import ReconstructionError
from ..relay import Relay
from .blas import blas_threads
from .chunks import run_chunks
from .gram import chunk_gram
from .jit import compiled as _compiled
from .grid import DepthGrid
from .physics import BRDFS, cell_variance, footprint_variance, relay_amplitude, relay_delay
from .response import Response

__all__ = ["SurfaceModel", "SurfaceState"]


#: the largest chunk of a prediction (bytes): its ragged window arrays stay in the cache (32 x 32
#: nodes, the resolution chart's 256 traces, 2 threads: 2.14 s a prediction in chunks of 192 MiB,
#: most of it page faults and memory traffic; 0.52 s at 12 MiB, 0.71 s at 24; the same numbers)
PREDICT_CHUNK_BYTES = 12 * 2 ** 20


def _symmetrise(L: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose lower triangle is ``L``'s."""
    return np.tril(L) + np.tril(L, -1).T


@dataclass
class SurfaceState:
    """The unknowns of one level: depths and albedos per node, the response's core width and
    tail and its slow tails' weights, the background level b0 and the direct return's decay
    (amplitude b1, length tau_b; metres of path)."""

    z: np.ndarray
    rho: np.ndarray
    sigma: float
    tail: float
    betas: tuple
    bg: float
    bg1: float = 0.0
    bgtau: float = 0.1
    #: (K, 2) in-plane centroid offsets (along u, v; metres) of the cells of the model's
    #: ``offset_nodes`` (a cell the surface's edge cuts emits from its covered part), then with
    #: ``cell_extent`` (K, 4): also the shrink (s_u, s_v) of the emitting part's extent, and with
    #: ``cell_shear`` (K, 5): its shear k; or None
    off: np.ndarray | None = None

    def copy(self) -> "SurfaceState":
        return replace(self, z=np.array(self.z, float), rho=np.array(self.rho, float),
                       off=None if self.off is None else np.array(self.off, float))


class SurfaceModel:
    """Forward model and Gauss-Newton pieces of one level (grid, relay window, response).

    Parameters
    ----------
    grid : the level's depth grid.
    relay : the traces (already cut to the level's time window).
    response : the response's kind and slow-tail lengths (its numbers are the state's).
    brdf : "lambertian" or "retroreflective" (confocal relays only).
    fit_shape : the response's width, tail and slow-tail weights are unknowns; else only the
        background is.
    chunk_bytes : memory of one chunk's dense Jacobian rows.
    subsamples : q: each node's cell is integrated by q x q sub-samples on the node's tangent
        plane (each with its own delay, amplitude and sub-cell spread), so cells wider than the
        response's width are not reduced to one moment-matched Gaussian.
    direct : per-trace amplitude q_p of the relay's own return (its slow decay enters the
        background), or None.
    workers : threads over the trace chunks of ``predict`` / ``linearise`` (the compiled
        geometry, NumPy's ufuncs and BLAS release the GIL); the chunks' sums are added in chunk
        order, so the numbers are the same bit for bit whatever the count (memory: a chunk per
        worker).
    offset_nodes : nodes whose cell emits from an in-plane centroid offset (ox, oy) that is
        itself an unknown (``SurfaceState.off``; packed after the globals): a cell the surface's
        edge cuts is covered on one side only, and a uniform cell at the node puts its return
        at the wrong delay (measured: seeded twins' depth errors of 5-8 std over the whole
        surface, its claims' coverage 0.58 -> 0.84 with the true centroids given).
    cell_extent : the offset nodes' cells also emit from a part (1 - s_u) x (1 - s_v) of the
        cell's sides (its sub-samples and delay spread shrink about the centroid; the area, and
        so the albedo's meaning, stay the cell's), s_u, s_v unknowns packed after each offset.
    cell_shear : with ``cell_extent``, the emitting part is a parallelogram, not a rectangle: its
        v side leans by k (a sub-sample at (du, dv) of the cell sits at (du fu + k dv, dv fv) from
        the centroid), unknowns packed after the shrinks. Its second moments are then any 2 x 2
        covariance (a Cholesky factor): a triangle cut by an oblique edge has a u-v covariance
        that no axis-aligned rectangle has.
    """

    def __init__(self, grid: DepthGrid, relay: Relay, response: Response, brdf: str = "lambertian",
                 fit_shape: bool = True, chunk_bytes: int = 192 * 2 ** 20, subsamples: int = 1,
                 direct: np.ndarray | None = None, workers: int = 1, offset_nodes=None, cell_extent=False,
                 cell_shear=False):
        if brdf not in BRDFS:
            raise ReconstructionError(f"brdf must be one of {BRDFS}; got {brdf!r}.")
        if brdf == "retroreflective" and not relay.confocal:
            raise ReconstructionError("A retroreflective surface returns light only to the laser's own "
                                      "spot: brdf='retroreflective' needs a confocal relay. Use "
                                      "brdf='lambertian' for paired or full-STIR relays.")
        self.grid, self.relay, self.brdf = grid, relay, brdf
        self.kind, self.taus = response.kind, tuple(t for t, _ in response.slow)
        g = relay.grid
        self.w, self.T, self.t_start = g.bin_width, g.n_bins, g.start
        self.P, self.N = relay.n_traces, grid.n
        self.Gx, self.Gy = grid.gradient_ops()
        Dxx, Dyy, Dxy = grid.curvature_ops()
        # the six local unknowns of a node's patch (z, gx, gy, zxx, zyy, zxy) from the depths
        self.ops = [None, self.Gx, self.Gy, Dxx, Dyy, Dxy]
        self.opsT = [None] + [o.T.tocsr() for o in self.ops[1:]]
        # the chain rule of the Jacobian in one sparse product: local columns (6 N) -> depths
        self.ops_stack = sp.vstack([sp.identity(self.N, format="csr")] + self.ops[1:]).tocsr()
        self.base = grid.base_points()
        self.t_left = g.start + np.arange(self.T) * self.w
        self.direct = None if direct is None else np.asarray(direct, float)
        shape = []
        if fit_shape:
            shape = ["sigma"] + (["tail"] if self.kind == "emg" else []) + [f"beta{i}" for i in range(len(self.taus))]
        self.glob = shape + ["bg"] + (["bg1", "bgtau"] if self.direct is not None else [])
        self.chunk_bytes = int(chunk_bytes)
        self.workers = max(1, int(workers))
        self.sub = max(1, int(subsamples))
        self.footprint = bool(np.any(relay.footprint > 0))
        on = np.zeros(0, int) if offset_nodes is None else np.unique(np.asarray(offset_nodes, int))
        if on.size and (on.min() < 0 or on.max() >= self.N):
            raise ReconstructionError(f"offset_nodes must be node indices in 0..{self.N - 1}; got {on.min()}..{on.max()}.")
        self.onodes, self.K = on, int(on.size)
        self.extent = bool(cell_extent)
        self.shear = bool(cell_shear) and self.extent
        self.E = 2 + 2 * self.extent + self.shear      # unknowns per offset node (ox, oy[, s_u, s_v[, k]])
        self._build()
        self._maps: dict = {}

    # ------------------------------------------------------------------ parameters
    @property
    def npar(self) -> int:
        return 2 * self.N + len(self.glob) + self.E * self.K

    @staticmethod
    def _get(st: SurfaceState, name: str) -> float:
        return float(st.betas[int(name[4:])]) if name.startswith("beta") else float(getattr(st, name))

    def pack(self, st: SurfaceState) -> np.ndarray:
        return np.concatenate([st.z, st.rho, [self._get(st, k) for k in self.glob], self.centroid_offsets(st).ravel()])

    def centroid_offsets(self, st: SurfaceState) -> np.ndarray:
        """The state's (K, E) centroid offsets [and shrinks] (zeros where it holds none; a
        state's (K, 2) offsets get zero shrinks, and (K, 4) a zero shear)."""
        if st.off is None or self.K == 0:
            return np.zeros((self.K, self.E))
        off = np.asarray(st.off, float)
        if off.ndim == 2 and off.shape[0] == self.K and off.shape[1] < self.E:   # nested: zeros
            off = np.hstack([off, np.zeros((self.K, self.E - off.shape[1]))])
        if off.shape != (self.K, self.E):
            raise ReconstructionError(f"The state's offsets have shape {off.shape}; the model has {self.K} offset nodes.")
        return off

    def unpack(self, theta: np.ndarray, like: SurfaceState) -> SurfaceState:
        N = self.N
        kw, betas = {}, list(like.betas)
        for i, k in enumerate(self.glob):
            if k.startswith("beta"):
                betas[int(k[4:])] = float(theta[2 * N + i])
            else:
                kw[k] = float(theta[2 * N + i])
        g1 = 2 * N + len(self.glob)
        off = np.array(theta[g1:g1 + self.E * self.K], float).reshape(self.K, self.E) if self.K else None
        return replace(like, z=np.array(theta[:N], float), rho=np.array(theta[N:2 * N], float),
                       betas=tuple(betas), off=off, **kw)

    def seen(self, rho: np.ndarray, frac: float = 0.02) -> np.ndarray:
        """Nodes whose depth the data constrain: their albedo or a 4-neighbour's (through the
        normal) is at least ``frac`` of the largest."""
        on = (np.asarray(rho) > frac * max(float(np.max(rho)), 1e-300)).reshape(self.grid.shape)
        near = on.copy()
        near[1:] |= on[:-1]
        near[:-1] |= on[1:]
        near[:, 1:] |= on[:, :-1]
        near[:, :-1] |= on[:, 1:]
        return near.ravel()

    def response(self, st: SurfaceState) -> Response:
        return Response(self.kind, st.sigma, st.tail if self.kind == "emg" else 0.0,
                        tuple(zip(self.taus, st.betas)))

    def background(self, st: SurfaceState, t0: int = 0, t1: int | None = None):
        """b_pk of traces t0..t1 (see the module equation) and, with a direct return, its
        derivatives with respect to b1 and tau_b."""
        t1 = self.P if t1 is None else t1
        b = np.full((t1 - t0, self.T), float(st.bg))
        if self.direct is None:
            return b, None, None
        dt = self.t_left - self.t_start
        e = np.exp(-dt / st.bgtau)
        d1 = self.direct[t0:t1, None] * e[None, :]
        return b + st.bg1 * d1, d1, st.bg1 * d1 * (dt / st.bgtau ** 2)[None, :]

    # ------------------------------------------------------------------ CasADi pair geometry
    def _build(self):
        c, u, v, wv = (ca.DM(np.asarray(a, float)) for a in self.grid.frame)
        # z, gx, gy, zxx, zyy, zxy of the node, its cell's centroid ox, oy [shrink su, sv [shear k]]
        p = ca.SX.sym("p", 6 + self.E)
        q = ca.SX.sym("q", 21)         # Xb(3) L(3) D(3) nL(3) nD(3) leg gain fu2 fv2 dx dy
        z, gx0, gy0, zxx, zyy, zxy, ox, oy = (p[i] for i in range(8))
        fu, fv = (1 - p[8], 1 - p[9]) if self.extent else (1.0, 1.0)
        k = p[10] if self.shear else 0.0
        dx, dy = (q[19] * fu + k * q[20] + ox, q[20] * fv + oy) if self.extent else (q[19] + ox, q[20] + oy)
        # the sub-sample at in-plane offset (dx, dy) from the node (its cell's centroid moved by
        # (ox, oy)) lies on the node's second-order patch
        gx = gx0 + zxx * dx + zxy * dy
        gy = gy0 + zxy * dx + zyy * dy
        s = ca.sqrt(1 + gx ** 2 + gy ** 2)
        ex, ey = (ox - q[19] * p[8] + k * q[20], oy - q[20] * p[9]) if self.extent else (ox, oy)
        X = (q[0:3] + ex * u + ey * v
             + (z + gx0 * dx + gy0 * dy + 0.5 * (zxx * dx * dx + zyy * dy * dy) + zxy * dx * dy) * wv)
        nX = -(wv - gx * u - gy * v) / s
        hx, hy = self.grid.hx / self.sub, self.grid.hy / self.sub
        area = hx * hy * s
        L, D = q[3:6], q[6:9]
        amp = relay_amplitude(L, D, q[9:12], q[12:15], X, nX, area, 1.0, q[16], brdf=self.brdf)
        tau = relay_delay(L, D, X, q[15])
        tu, tv = u + gx * wv, v + gy * wv      # the sub-cell's sides hx fu tu and hy (k tu + fv tv)
        c2 = (cell_variance(L, D, X, tu, k * tu + fv * tv, hx * fu, hy) if self.shear
              else cell_variance(L, D, X, tu, tv, hx * fu, hy * fv))    # (fu = 1: exact)
        if self.footprint:     # a trace summing several scan points (Relay.footprint)
            c2 = c2 + footprint_variance(L, D, X, u, v, q[17], q[18])
        out = ca.vertcat(amp, tau, c2)
        # the same function with q split into the sub-sample's own numbers nd = (Xb, dx, dy)
        # and the trace's tr = (L, D, nL, nD, leg, gain, footprint): mapped over a trace's node
        # samples with tr shared, then over the traces with p and nd shared, so the inputs are
        # (6 + 5) x N S + 16 x traces numbers instead of 27 x traces x N S (converting those took
        # longer than evaluating the map)
        nd, tr = ca.SX.sym("nd", 5), ca.SX.sym("tr", 16)
        q_of = ca.vertcat(nd[0:3], tr, nd[3:5])
        jac = ca.vertcat(out, ca.vec(ca.jacobian(out, p)))
        self.f_geo = _compiled(ca.Function("pair_geometry", [p, nd, tr], [ca.substitute(out, q, q_of)]))
        self.f_geo_jac = _compiled(ca.Function("pair_geometry_jac", [p, nd, tr], [ca.substitute(jac, q, q_of)]))
        k = (np.arange(self.sub) + 0.5) / self.sub - 0.5
        dy, dx = np.meshgrid(k * self.grid.hy, k * self.grid.hx, indexing="ij")
        self.offsets = np.stack([dx.ravel(), dy.ravel()], axis=1)          # (S, 2)

    def _mapped(self, n_samples: int, n_traces: int, jac: bool):
        key = (n_samples, n_traces, jac)
        if key not in self._maps:
            if len(self._maps) > 8:
                self._maps.clear()
            f = self.f_geo_jac if jac else self.f_geo
            inner = f.map("samples", "serial", n_samples, [2], [])        # tr shared
            self._maps[key] = inner.map("traces", "serial", n_traces, [0, 1], [])   # p, nd shared
        return self._maps[key]

    def _geometry(self, t0: int, t1: int, loc, jac: bool):
        """(K, S, 3) values (A, tau, c^2) of the K = traces x nodes pairs' S sub-samples and,
        with ``jac``, (K, S, 3, 8) d(A, tau, c^2) / d(z, gx, gy, zxx, zyy, zxy, ox, oy) (``loc``:
        those eight per node)."""
        r, N = self.relay, self.N
        S = len(self.offsets)
        nt = t1 - t0
        _, u, v, _ = self.grid.frame
        # CasADi's dense matrices are column-major: a (rows, cols) input is a C-ordered
        # (cols, rows) NumPy array, handed over and filled in place through the function's
        # buffer (converting to and from DM took longer than the compiled map itself)
        Pm = np.ascontiguousarray(np.repeat(np.stack(loc, axis=1), S, axis=0))     # (N S, 6 + E)
        off = np.tile(self.offsets, (N, 1))                                        # (N S, 2)
        Xb = np.repeat(self.base, S, axis=0) + off[:, :1] * u[None] + off[:, 1:] * v[None]
        nd = np.ascontiguousarray(np.hstack([Xb, off]))                            # (N S, 5)
        tr = np.ascontiguousarray(np.hstack([r.L[t0:t1], r.D[t0:t1], r.nL[t0:t1], r.nD[t0:t1],
                                             r.leg[t0:t1, None], r.gain[t0:t1, None],
                                             r.footprint[t0:t1]]))                       # (nt, 16)
        npl = 6 + self.E
        out = np.empty((nt * N * S, 3 + 3 * npl if jac else 3))
        buf, run = self._mapped(N * S, nt, jac).buffer()
        for i, a in enumerate((Pm, nd, tr)):
            buf.set_arg(i, memoryview(a))
        buf.set_res(0, memoryview(out))
        run()
        vals = out[:, :3].reshape(nt * N, S, 3)
        if not jac:
            return vals, None
        return vals, out[:, 3:].reshape(nt * N, S, npl, 3).transpose(0, 1, 3, 2)   # [k, s, output, input]

    # ------------------------------------------------------------------ response windows
    def _windows(self, st: SurfaceState, resp: Response, tau, c2, need_parts: bool, need_tail: bool,
                 active: np.ndarray | None = None, lit: np.ndarray | None = None):
        """The bins each pair reaches (shared by its sub-samples), ragged: each pair p gets its
        own window of n_p bins, from its earliest sub-sample delay plus the core's left support
        to its latest plus the right support at the pair's own widest sub-sample, cut to the
        record (bins outside it are dropped anyway; a bin's integral does not depend on the
        window it sits in, so the cut is exact). One wide pair no longer lengthens every window.

        Returns a dict: ``pe`` (E,) the pair of each window bin, ``kk`` (E,) its bin index,
        ``s`` (K, S) the per-sample widths, ``B`` (E, S) the core's bin integrals and, with
        ``need_parts``, ``dF`` / ``dF1`` [/ ``dFt``] (E, S): the bin differences of f, f'
        [and dF/dtail] (their edge values differenced over each bin). ``active`` (N,): the
        nodes whose pairs get windows (the others none: their bins drop out of every sum).
        ``lit`` (N,): the nodes whose bins need ``dF`` / ``dF1`` [/ ``dFt``] (every sum they
        enter carries the node's albedo as a factor): where some node is not lit, these come
        for the bins ``out["lit"]`` only (else ``out["lit"]`` is None)."""
        s = np.sqrt(st.sigma ** 2 + c2)
        K = tau.shape[0]
        w = self.w
        lo, hi = resp.support(s.max(axis=1) if s.size else np.full(K, st.sigma))
        tmin, tmax = tau.min(axis=1), tau.max(axis=1)
        k0 = np.floor((tmin + lo - self.t_start) / w).astype(np.int64)
        n = np.ceil((tmax - tmin + hi - lo) / w).astype(np.int64) + 2
        a = np.clip(k0, 0, self.T)
        b = np.clip(k0 + n, 0, self.T)
        n = b - a                                        # bins of each pair inside the record
        if active is not None:
            n = np.where(np.tile(active, K // self.N), n, 0)
        ne = np.where(n > 0, n + 1, 0)                   # edges of each pair's window
        eo = np.concatenate([[0], np.cumsum(ne)])
        E_edge = int(eo[-1])
        ep = np.repeat(np.arange(K), ne)                 # pair of each edge
        je = np.arange(E_edge) - eo[ep]                  # edge offset inside its window
        x = (self.t_start + (np.take(a, ep) + je)[:, None] * w - np.take(tau, ep, axis=0) + resp.mode_offset())
        se = np.take(s, ep, axis=0)
        # bin i of pair p: edges eo_p + i (left) and eo_p + i + 1 (right): every edge but each
        # window's last is a left edge (rows ``li``), so a bin's difference is F[li + 1] - F[li]
        # (np.diff masked by ``left``, the same numbers, took 6.5 ms a (262 000, 4) array, this 3.7)
        pe = np.repeat(np.arange(K), n)
        i = np.arange(len(pe)) - np.repeat(np.cumsum(n) - n, n)            # bin offset in its window
        left = np.ones(E_edge, bool)
        left[eo[1:][ne > 0] - 1] = False
        li = np.flatnonzero(left[:-1])
        out = {"pe": pe, "kk": a[pe] + i, "s": s}
        if not need_parts:
            F = resp.cdf(x, se)
            out["B"] = np.take(F, li + 1, axis=0) - np.take(F, li, axis=0)
            return out
        out["lit"] = le = None
        if lit is not None and not np.all(lit):
            lp = np.tile(lit, K // self.N)
            on = np.take(lp, ep)                                        # the lit pairs' edges
            le = np.flatnonzero(on)
            out["lit"] = lb = np.flatnonzero(np.take(lp, pe))
            at = np.take(np.cumsum(on) - 1, np.take(li, lb))             # their left edges among le
        parts = resp.parts(x, se, need_tail=need_tail, rows=le)
        for key, arr in zip(("B", "dF", "dF1", "dFt"), parts):
            l0 = li if (le is None or key == "B") else at
            out[key] = np.take(arr, l0 + 1, axis=0) - np.take(arr, l0, axis=0)
        return out

    def _chunks(self, per_trace_bytes: int, cap: int | None = None):
        size = self.chunk_bytes if cap is None else min(self.chunk_bytes, cap)
        nt = max(1, int(size // max(per_trace_bytes, 1)))
        for t0 in range(0, self.P, nt):
            yield t0, min(t0 + nt, self.P)

    def _each_chunk(self, fn, per_trace_bytes: int, cap: int | None = None):
        """``fn(t0, t1)`` over the trace chunks on ``self.workers`` threads (``chunks.py``)."""
        return run_chunks(fn, list(self._chunks(per_trace_bytes, cap)), self.workers)

    # ------------------------------------------------------------------ evaluation
    def _local(self, z, st: SurfaceState | None = None):
        """The 6 + E local unknowns of every node's patch (``ops`` applied to the depths; the
        centroid offsets [and shrinks], zero but at ``onodes``)."""
        extra = np.zeros((self.E, self.N))
        if self.K and st is not None:
            extra[:, self.onodes] = self.centroid_offsets(st).T
        return [z] + [o @ z for o in self.ops[1:]] + list(extra)

    def _core(self, st, resp, t0, t1, loc):
        """Binned core deposits G (nt, T) of traces t0..t1 (no slow tails, no background)."""
        G, _ = self._geometry(t0, t1, loc, False)
        # a node of albedo zero deposits exact zeros: its pairs get no window
        win = self._windows(st, resp, G[..., 1], G[..., 2], False, False, st.rho != 0)
        pe = win["pe"]
        val = np.einsum("es,es->e", np.take(G[..., 0], pe, axis=0), win["B"]) * np.take(np.tile(st.rho, t1 - t0), pe)
        nt = t1 - t0
        return np.bincount(self._rows(pe, win["kk"]), val, minlength=nt * self.T).reshape(nt, self.T)

    def predict(self, st: SurfaceState) -> np.ndarray:
        """Model traces (P, T)."""
        resp = self.response(st)
        loc = self._local(st.z, st)
        out = np.empty((self.P, self.T))
        S = len(self.offsets)

        def one(t0, t1):
            G = self._core(st, resp, t0, t1, loc)
            out[t0:t1] = self.background(st, t0, t1)[0] + resp.tail_filter(G, self.w)

        for _ in self._each_chunk(one, self.N * S * 8 * 64, cap=PREDICT_CHUNK_BYTES):
            pass
        return out

    def _rows(self, pe, kk):
        """Chunk-local row (trace * T + bin) of window bins of pairs ``pe`` (pairs are ordered
        trace-major, N per trace) at bins ``kk``."""
        return (pe // self.N) * self.T + kk

    def linearise(self, st: SurfaceState, y: np.ndarray, wgt: np.ndarray, dtype=np.float32,
                  need_h: bool = True, skip: np.ndarray | None = None) -> dict:
        """Model, whitened chi^2, gradient g = J^T W (m - y) and (``need_h``) the Gauss-Newton
        matrix H = J^T W J over ``pack``'s parameters, accumulated in float64 from chunk
        products in ``dtype``. Returns dict(m, chi2, g, H). ``skip`` (N,): nodes of albedo zero
        whose albedo is held there (a solver's; not for a Fisher matrix): their pairs are not formed,
        so their albedo's entries of g and H come out zero; every other entry is unchanged (the
        pairs' other derivatives, and their deposits, carry the albedo as a factor)."""
        resp = self.response(st)
        N, T, w = self.N, self.T, self.w
        S = len(self.offsets)
        z, rho = st.z, st.rho
        lz = self._local(z, st)
        need_tail = "tail" in self.glob
        dm = resp.d_mode()
        npar = self.npar
        g = np.zeros(npar)
        m = np.empty((self.P, T))
        chi2 = 0.0
        itemsize = np.dtype(dtype).itemsize
        slow = bool(resp.slow)
        active = None
        if skip is not None and np.any(skip):
            if np.any(rho[skip] != 0):
                raise ReconstructionError("linearise(skip=...): a skipped node's albedo must be zero.")
            active = ~np.asarray(skip, bool)
        # the depth columns the lit nodes' stencils reach (the others are exact zeros: not formed)
        zkeep = keep = None
        if need_h and not np.all(rho != 0):
            reach = np.zeros(N, bool)
            reach[self.ops_stack[(np.arange(6)[:, None] * N + np.flatnonzero(rho)).ravel()].indices] = True
            if not reach.all():
                zkeep = np.flatnonzero(reach)
                keep = np.concatenate([zkeep, np.arange(N, npar)])
        H = np.zeros((npar, npar) if keep is None else (len(keep), len(keep))) if need_h else None

        def one(t0, t1):
            nt = t1 - t0
            G, Jg = self._geometry(t0, t1, lz, True)
            A, tau, c2 = G[..., 0], G[..., 1], G[..., 2]                    # (K, S)
            # (the bins of a zero albedo, dark nodes LM holds at the bound: 25-65 % of the 32 x 32
            # chart's, carry rho as a factor of every derivative but the albedo's: exact zeros,
            # not formed; ``lit``: the others, None where every albedo is non-zero)
            win = self._windows(st, resp, tau, c2, True, need_tail, active, rho != 0)
            pe, Bw, dF, dF1, lit = win["pe"], win["B"], win["dF"], win["dF1"], win["lit"]   # (E,), (E, S)
            # (np.take: the same rows as fancy indexing, gathered faster)
            s = np.take(win["s"], pe, axis=0)
            rr = np.take(np.tile(rho, nt), pe)[:, None]
            Ae = np.take(A, pe, axis=0)
            Ar = Ae * rr
            rows_loc = self._rows(pe, win["kk"])

            def to_rows(v, at=rows_loc):     # window bins' values at rows ``at`` -> (nt, T) binned
                return np.bincount(at, v, minlength=nt * T).reshape(nt, T)

            Gc = to_rows(np.sum(Ar * Bw, axis=1))
            bgc, d_b1, d_bt = self.background(st, t0, t1)
            mc = bgc + resp.tail_filter(Gc, w)
            rc = mc - y[t0:t1]
            wc = wgt[t0:t1]
            m[t0:t1] = mc
            chi2c = float(np.sum(wc * rc * rc))
            # local derivatives (E,), summed over the sub-samples: the six patch unknowns, rho
            #   d m / d p_c = sum_s rho B dA_c + rho A (s dF1 ds_c - dF dtau_c): the window bins'
            #   factors (E, 3 S) once, the pairs' derivatives (K, 3 S) per unknown, one product
            ds = Jg[:, :, 2, :] / (2.0 * win["s"][:, :, None])             # d s / d(patch), (K, S, 8)
            S3 = Bw.shape[1]
            pl = pe if lit is None else np.take(pe, lit)

            def on_lit(a):
                return a if lit is None else np.take(a, lit, axis=0)
            Arl, rows_l = on_lit(Ar), on_lit(rows_loc)
            Q = np.empty((len(pl), 3 * S3))
            np.multiply(on_lit(rr), on_lit(Bw), out=Q[:, :S3])
            np.multiply(Arl, on_lit(s) * dF1, out=Q[:, S3:2 * S3])
            np.multiply(-Arl, dF, out=Q[:, 2 * S3:])
            # the gradient in float64 (exact, whatever ``dtype``): the slow tails' adjoint first;
            # a local unknown's sum over its node's bins (the patch derivatives over the lit ones)
            e = wc * rc
            ef = resp.tail_filter(e, w, adjoint=True)
            node = pe % N
            er = ef.ravel()[rows_loc]
            nl, erl = (node, er) if lit is None else (np.take(node, lit), np.take(er, lit))
            # the lit bins' derivatives ``dv``: rows 0-5 the patch's unknowns, 6.. the centroid
            # offsets [shrinks] (with any); the albedo's ``la`` over every bin; their node sums
            # ``gl``: rows 0-5 the patch's, 6 the albedo's, 7.. the offsets'
            nd = 6 + self.E if self.K else 6
            dv = np.empty((nd, len(pl)))
            gl = np.empty((nd + 1, N))
            for c in range(nd):
                Cc = np.hstack([Jg[:, :, 0, c], ds[:, :, c], Jg[:, :, 1, c]])
                dv[c] = np.einsum("ej,ej->e", Q, np.take(Cc, pl, axis=0))
                gl[c if c < 6 else c + 1] = np.bincount(nl, dv[c] * erl, minlength=N)
            la = np.sum(Ae * Bw, axis=1)
            gl[6] = np.bincount(node, la * er, minlength=N)
            # global columns, binned: core ones before the slow tails (list pre), others after
            shift = to_rows(np.sum(Arl * dF, axis=1), rows_l)               # d G / d m0
            pre, post = [], []
            for name in self.glob:
                if name == "sigma":
                    pre.append(to_rows(np.sum(Arl * st.sigma * dF1, axis=1), rows_l) + dm[0] * shift)
                elif name == "tail":
                    pre.append(to_rows(np.sum(Arl * win["dFt"], axis=1), rows_l) + dm[1] * shift)
                elif name.startswith("beta"):
                    i = int(name[4:])
                    from .response import exp_filter
                    post.append(exp_filter(Gc, self.taus[i], w) - Gc + dm[2 + i] * resp.tail_filter(shift, w))
                elif name == "bg":
                    post.append(np.ones((nt, T)))
                elif name == "bg1":
                    post.append(d_b1)
                else:
                    post.append(d_bt)
            gc = np.zeros(npar)
            gc[:N] = gl[0] + sum(self.opsT[c] @ gl[c] for c in range(1, 6))
            gc[N:2 * N] = gl[6]
            gcols = [float(np.sum(c * ef)) for c in pre] + [float(np.sum(c * e)) for c in post]
            g1 = 2 * N + len(gcols)
            gc[2 * N:g1] = gcols
            if self.K:
                gc[g1:] = np.stack([gl[7 + e][self.onodes] for e in range(self.E)], axis=1).ravel()
            if not need_h:
                return chi2c, gc, None
            return chi2c, gc, chunk_gram(self, nt, rows_loc, node, rows_l, nl, dv, la, pre, post, wc, resp, dtype,
                                         zkeep)
        # the chunks' sums in chunk order (the same numbers on any number of workers)
        # (chunks on worker threads: each syrk on one BLAS thread, off the GIL, ``blas.py``; one chunk: serial)
        chunks = list(self._chunks(max(T * 7 * N * itemsize * (2 if slow else 1), N * S * 8 * 64 * 9)))
        with blas_threads(1 if self.workers > 1 and len(chunks) > 1 else None):
            for chi2c, gc, Hc in run_chunks(one, chunks, self.workers):
                chi2 += chi2c
                g += gc
                if need_h:
                    H += Hc
        if keep is not None:
            H, Hk = np.zeros((npar, npar)), H
            H[np.ix_(keep, keep)] = Hk
        return {"m": m, "chi2": chi2, "g": g, "H": None if H is None else _symmetrise(H)}   # (H: lower triangle)

    def objective(self, st: SurfaceState, y, wgt) -> tuple[float, np.ndarray]:
        """(chi^2, model) at ``st``."""
        m = self.predict(st)
        return float(np.sum(wgt * (m - y) ** 2)), m
