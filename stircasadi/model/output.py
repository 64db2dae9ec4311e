"""The model's STIR: path amplitudes and delays (one formula, NumPy or CasADi) binned by the IRF.

A path source -> v_1 -> ... -> v_n -> camera carries

    a = (phi / a_{v_1}) * prod_m f_{v_m}(w_in, w_out) * prod_legs G_leg
    tau = |s - z_{v_1}| + sum_legs length + |z_{v_n} - o|        (end legs when ``legs_included``)

with f the vertex's BRDF (``stircasadi.brdf`` formulas; the general tabulated f_kij where
declared; albedo / area for a patch whose albedo unknown is the product albedo x area) and G, the
lengths and the directions from ``radiometry.direct_leg`` / ``radiometry.mirror_leg`` — the
same functions the numeric transport (``transport/system.py``) uses. Each path adds
``a * B(t_k - tau, w)`` to the bins k of its trace, ``B = irf.bin_integral``.

Structure: a path none of whose vertices moves has a constant kernel (a column of a sparse
matrix ``A_fixed``) times a symbolic amplitude; a path with a moving vertex gets a symbolic
kernel on its window, scattered by a constant 0/1 matrix. ``OutputStructure`` documents what the
NLP may use (it never reads the model's private state).
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy import sparse

from .. import _backend as B
from ..brdf import Lambertian, Phong
from ..irf import bin_integral
from ..radiometry import direct_leg, mirror_leg, source_irradiance, vdot, vnorm, vscale, vsub

__all__ = ["OutputStructure", "path_terms", "build_output", "numeric_stir"]


@dataclass
class OutputStructure:
    """The symbolic STIR on the support bins, and its parts for structured costs.

    y : MX (n_support,) the model STIR on the support (elsewhere it is exactly zero).
    support : (n_support,) flat indices into ``stir.reshape(-1)``; support_trace : their trace.
    seg_start : (n_traces + 1,) the support bins of trace t are ``seg_start[t]:seg_start[t+1]``.
    A_fixed : scipy CSC (n_support, n_fixed) constant kernels of the fixed paths, or None.
    amp_fixed : MX (n_fixed,) their symbolic amplitudes. y_var : MX, the moving paths' part.
    fixed_trace : (n_fixed,) trace of each fixed path. variable_traces : (n_traces,) bool.
    """

    y: object
    support: np.ndarray
    support_trace: np.ndarray
    seg_start: np.ndarray
    A_fixed: object
    amp_fixed: object
    y_var: object
    fixed_trace: np.ndarray
    variable_traces: np.ndarray
    n_paths: int
    n_variable_paths: int


def _take(e, idx):
    return e[:, idx.tolist()] if B.is_symbolic(e) else np.asarray(e)[idx]


def _const(v, like):
    """A numeric per-path row in the backend of ``like``."""
    return ca.DM(np.asarray(v, float)).T if B.is_symbolic(like) else np.asarray(v, float)


def path_terms(vq: dict, verts: np.ndarray, via: tuple, model, fkij=None):
    """(amplitude, tau) of the paths ``verts`` (P, n) sharing the mirror signature ``via``;
    ``vq`` are vertex quantities (``vertices.vertex_quantities``), NumPy or CasADi."""
    n = verts.shape[1]
    sym = B.is_symbolic(vq["albedo"])
    cols = [verts[:, m] for m in range(n)]
    z = [tuple(_take(c, cols[m]) for c in vq["z"]) for m in range(n)]
    nn = [tuple(_take(c, cols[m]) for c in vq["n"]) for m in range(n)]
    src = tuple(float(c) for c in model.source)
    cam = tuple(float(c) for c in model.camera)
    legs = []
    for m in range(n - 1):
        a_src = _take(vq["area"], cols[m])
        if via[m] < 0:
            legs.append(direct_leg(z[m], z[m + 1], nn[m], nn[m + 1], a_src))
        else:
            mp = via[m]
            legs.append(mirror_leg(z[m], z[m + 1], nn[m], nn[m + 1], a_src,
                                   tuple(float(c) for c in model.z0[mp]),
                                   tuple(float(c) for c in model.normals[mp]),
                                   model.mirrors[mp].reflectance))
    to_src = vsub(src, z[0])
    d_src = vnorm(to_src)
    to_cam = vsub(cam, z[-1])
    d_cam = vnorm(to_cam)
    w_prev = [vscale(to_src, 1.0 / d_src)] + [lg.dir_in for lg in legs]
    w_next = [lg.dir_out for lg in legs] + [vscale(to_cam, 1.0 / d_cam)]
    patch = model.layout.patch
    amp = source_irradiance(model.phi_sym if sym else vq.get("phi", model.phi), _take(vq["area"], cols[0]))
    for m in range(n):
        ci, co, cio = vdot(w_prev[m], nn[m]), vdot(w_next[m], nn[m]), vdot(w_prev[m], w_next[m])
        pk = patch[cols[m]]
        rho = _take(vq["albedo"], cols[m])
        prod = model.albedo_product[pk]
        if prod.any():
            pa = _take(vq["patch_area"], cols[m])
            mk = _const(prod, rho)
            rho = mk * rho / pa + (1 - mk) * rho
        f = Lambertian.formula(ci, co, cio, rho)
        gl = model.glossy[pk]
        if gl.any():
            fp = Phong.formula(ci, co, cio, rho, _take(vq["specular"], cols[m]), _take(vq["exponent"], cols[m]))
            mk = _const(gl, f)
            f = mk * fp + (1 - mk) * f
        ge = model.general[pk]
        if ge.any():
            prev = patch[cols[m - 1]] if m > 0 else np.full(len(pk), -1)
            nxt = patch[cols[m + 1]] if m < n - 1 else np.full(len(pk), -2)
            idx = np.zeros(len(pk), int)
            idx[ge] = model.triple_index(prev[ge], pk[ge], nxt[ge])
            fg = fkij[idx.tolist()].T if sym else np.asarray(fkij)[idx]
            mk = _const(ge, f)
            f = mk * fg + (1 - mk) * f
        amp = amp * f
    tau = 0.0
    for lg in legs:
        amp = amp * lg.g
        tau = tau + lg.length
    if model.legs_included:
        tau = tau + d_src + d_cam
    if not sym:
        tau = np.broadcast_to(np.asarray(tau, float), (len(verts),))
    return amp, tau


def build_output(model, vq_sym: dict, vq_num: dict, fkij_sym=None, fkij_num=None) -> OutputStructure:
    """Assemble the symbolic STIR on the support (see the module docstring)."""
    grid, irf = model.grid, model.irf
    w, t0, nb = grid.bin_width, grid.start, grid.n_bins
    seg, lo_tr = model.seg_start, model.trace_lo
    n_sup = int(seg[-1])
    y_var = ca.MX(n_sup, 1)
    A_blocks, amps, ftr = [], [], []
    var_tr = np.zeros(len(lo_tr), bool)
    n_paths = n_var = 0
    for g in model.paths:
        n_paths += len(g.verts)
        for var in (False, True):
            sel = np.flatnonzero(g.variable == var)
            if not len(sel):
                continue
            verts = g.verts[sel]
            amp, tau_sym = path_terms(vq_sym, verts, g.via, model, fkij_sym)
            k0, k1 = g.k0[sel], g.k1[sel]
            kmax = int(np.max(k1 - k0))
            kk = k0[:, None] + np.arange(kmax)[None, :]
            valid = (kk >= 0) & (kk < nb) & (kk < k1[:, None])
            pi, mi = np.nonzero(valid)
            tr = g.trace[sel][pi]
            rows_ = seg[tr] + (kk[pi, mi] - lo_tr[tr])
            if not var:
                _, tau = path_terms(vq_num, verts, g.via, model, fkij_num)
                h = bin_integral(irf, t0 + kk * w - tau[:, None], w)
                vals = h[pi, mi]
                nz = vals != 0.0
                A_blocks.append(sparse.csc_matrix((vals[nz], (rows_[nz], pi[nz])), shape=(n_sup, len(sel))))
                amps.append(amp.T)
                ftr.append(g.trace[sel])
            else:
                n_var += len(sel)
                left = ca.DM(t0 + kk * w)
                H = bin_integral(irf, left - ca.repmat(tau_sym.T, 1, kmax), w)
                Cm = H * ca.repmat(amp.T, 1, kmax)
                colv = mi * len(sel) + pi
                Sc = ca.DM(ca.Sparsity.triplet(n_sup, len(sel) * kmax, rows_.tolist(), colv.tolist()),
                           np.ones(len(rows_)))
                y_var = y_var + ca.mtimes(Sc, ca.vec(Cm))
                var_tr[g.trace[sel]] = True
    if A_blocks:
        A = sparse.hstack(A_blocks).tocsc()
        amp_fixed = ca.vertcat(*amps)
        Acs = ca.DM(ca.Sparsity(A.shape[0], A.shape[1], A.indptr.tolist(), A.indices.tolist()), A.data)
        y = ca.mtimes(Acs, amp_fixed) + y_var
        fixed_trace = np.concatenate(ftr)
    else:
        A, amp_fixed, y, fixed_trace = None, None, y_var, np.zeros(0, int)
    return OutputStructure(y=y, support=model.support, support_trace=model.support_trace,
                           seg_start=seg, A_fixed=A, amp_fixed=amp_fixed, y_var=y_var,
                           fixed_trace=fixed_trace, variable_traces=var_tr, n_paths=n_paths,
                           n_variable_paths=n_var)


def numeric_stir(model, vq_num: dict, fkij_num=None, max_entries: int = 2_000_000) -> np.ndarray:
    """The model STIR at one numeric point, flat (n_traces * n_bins), by NumPy path sums: the
    same ``path_terms`` and ``irf.bin_integral`` as ``build_output`` on the same windows, with no
    CasADi graph (a probe, e.g. whether the next bounce order shows above the noise, costs the
    paths' arithmetic only). Paths are deposited in chunks of at most ``max_entries`` bins."""
    grid, irf = model.grid, model.irf
    w, t0, nb = grid.bin_width, grid.start, grid.n_bins
    out = np.zeros(len(model.ill_ids) * len(model.obs_ids) * nb)
    for g in model.paths:
        if not len(g.verts):
            continue
        amp, tau = path_terms(vq_num, g.verts, g.via, model, fkij_num)
        amp = np.broadcast_to(np.asarray(amp, float).ravel(), (len(g.verts),))
        span = np.maximum(g.k1 - g.k0, 0)
        step = max(1, int(max_entries // max(int(span.max()), 1)))
        for s0 in range(0, len(g.verts), step):
            sl = slice(s0, s0 + step)
            k0, k1 = g.k0[sl], g.k1[sl]
            kk = k0[:, None] + np.arange(int(span[sl].max()))[None, :]
            valid = (kk >= 0) & (kk < nb) & (kk < k1[:, None])
            h = bin_integral(irf, t0 + kk * w - tau[sl][:, None], w) * amp[sl][:, None]
            idx = (g.trace[sl][:, None] * nb + kk)[valid]
            if len(idx):  # summed over the bins the chunk touches, not the whole STIR
                lo = int(idx.min())
                part = np.bincount(idx - lo, weights=h[valid])
                out[lo:lo + len(part)] += part
    return out
