"""Hidden patches from the whole transient: a generalised-likelihood-ratio search of the residual.

When to use: after a fit of the known patches, to find returns no modelled patch explains. Unlike
a greedy onset budget, every trace and every bin of the residual votes.

Statistic. A point x lit by visible patch i and seen from visible patch j adds, to trace (i, j),
the pulse ``beta w_ij(x) g(t - tau_ij(x))`` with

    tau_ij(x) = r_i + |x - z_i| + |x - z_j| + c_j,
    w_ij(x)   = phi rho_i rho_j cos_i(x) cos_j(x) / (pi^3 |x - z_i|^2 |x - z_j|^2),

g the binned impulse response and beta = (albedo x area) x the hidden patch's two cosines (unknown,
>= 0). On whitened residuals R (noise std 1) the likelihood-ratio statistic for beta is

    T(x) = max(0, sum_ij w_ij m_ij(tau_ij))^2 / sum_ij w_ij^2 e_ij,

m_ij(tau) = sum_k R_ij[k] g_k(tau) (the matched filter) and e_ij = sum_k g_k^2; under noise alone
T is chi-square with one degree of freedom (halved). T is evaluated on a grid in front of the
visible patches (coarse, with each trace's matched filter dilated over half a grid step so no
peak falls between nodes), then maximised locally. The caller turns the best point into a
hidden patch, refits, and keeps it only when the whitened chi2 drops significantly.

Neglects: the hidden patch's own cosines (folded into beta), occlusion; an extended patch's
spread lowers its peak statistic but not its position.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter1d
from scipy.optimize import minimize

__all__ = ["Candidate", "matched_filters", "search"]


@dataclass
class Candidate:
    position: np.ndarray
    statistic: float
    beta: float
    normal: np.ndarray
    n_tested: int = 1   # grid points the statistic was maximised over (the look-elsewhere count)

    def significant(self, p: float = 1e-3) -> bool:
        """Whether T exceeds what noise alone reaches with probability ``p`` over the points
        tested (T of one point is a halved chi-square with one degree of freedom; Bonferroni over
        the grid). A screening test: the caller's likelihood-ratio refit decides."""
        from scipy.stats import chi2

        return self.statistic > chi2.isf(min(2.0 * p / max(self.n_tested, 1), 1.0), 1)


def matched_filters(R: np.ndarray, template, grid):
    """m(tau) of every trace on the bin centres: correlation of R (n, n_bins) with the binned
    response; returns (mf (n, n_bins), energy e, the template's offset in bins)."""
    from scipy.signal import fftconvolve

    w = grid.bin_width
    half = int(math.ceil(4.0 * template.width / w)) + 1
    x = np.arange(-half, half + 1) * w
    g, _ = template.pulse(x)
    # m_ij(tau at centre k) = sum_l R[l] g(c_l - c_k): correlation
    mf = fftconvolve(R, g[::-1][None, :], mode="same", axes=1)
    return mf, float(np.sum(g * g)), half


def _weights(x, z, n, rho, phi=1.0):
    """w_ij(x) for points x (G, 3): (G, M) factors per visible patch, product over i, j later."""
    v = x[:, None, :] - z[None, :, :]
    d = np.linalg.norm(v, axis=2)
    cos = np.einsum("gmd,md->gm", v, n) / d
    f = np.where(cos > 0, cos, 0.0) * rho[None, :] / (d * d)
    return f, d


def _T(points, ctx, dilated=False):
    """Statistic T and beta at points (G, 3)."""
    f, d = _weights(points, ctx["z"], ctx["n"], ctx["rho"])
    ii, jj = ctx["pi"], ctx["pj"]
    tau = ctx["r"][ii][None, :] + d[:, ii] + d[:, jj] + ctx["c"][jj][None, :]
    w = ctx["scale"] * f[:, ii] * f[:, jj]
    k = (tau - ctx["t0"]) / ctx["bw"] - 0.5
    k0 = np.floor(k).astype(int)
    frac = k - k0
    nb = ctx["nb"]
    inside = (k0 >= 0) & (k0 + 1 < nb)
    k0c = np.clip(k0, 0, nb - 2)
    mf = ctx["mfd"] if dilated else ctx["mf"]
    rows = np.broadcast_to(np.arange(len(ii))[None, :], k0.shape)
    m = (1 - frac) * mf[rows, k0c] + frac * mf[rows, k0c + 1]
    m = np.where(inside, m, 0.0)
    w = np.where(inside, w, 0.0)
    num = np.sum(w * m, axis=1)
    den = np.sum(w * w, axis=1) * ctx["e"]
    with np.errstate(invalid="ignore", divide="ignore"):
        beta = np.where(den > 0, num / den, 0.0)
        T = np.where((num > 0) & (den > 0), num * num / den, 0.0)
    return T, beta


def _spheroid(zi, zj, e, step):
    """Points of {x : |x - zi| + |x - zj| = e} sampled about every ``step`` metres."""
    c = 0.5 * (zi + zj)
    f = 0.5 * float(np.linalg.norm(zj - zi))
    a = 0.5 * e
    if a <= f + 1e-9:
        return np.zeros((0, 3))
    b = math.sqrt(a * a - f * f)
    u = (zj - zi) / (2 * f) if f > 1e-12 else np.array([0.0, 0.0, 1.0])
    v1 = np.cross(u, np.eye(3)[int(np.argmin(np.abs(u)))])
    v1 /= np.linalg.norm(v1)
    v2 = np.cross(u, v1)
    n_t = max(int(math.ceil(math.pi * a / step)), 8)
    th = (np.arange(n_t) + 0.5) * math.pi / n_t
    pts = []
    for t in th:
        rad = b * math.sin(t)
        n_p = max(int(math.ceil(2 * math.pi * rad / step)), 6)
        ph = np.arange(n_p) * 2 * math.pi / n_p
        pts.append(c + a * math.cos(t) * u + rad * (np.cos(ph)[:, None] * v1 + np.sin(ph)[:, None] * v2))
    return np.vstack(pts)


def _spheroid_area(zi, zj, e) -> float:
    """Surface area of the prolate spheroid {x : |x - zi| + |x - zj| = e} (0 when empty)."""
    f = 0.5 * float(np.linalg.norm(zj - zi))
    a = 0.5 * e
    if a <= f + 1e-9:
        return 0.0
    b = math.sqrt(a * a - f * f)
    ecc = f / a
    if ecc < 1e-6:
        return 4 * math.pi * a * a
    return 2 * math.pi * b * b * (1 + a / (b * ecc) * math.asin(ecc))


def search(R: np.ndarray, view, z, n, rho, template, step: float, max_traces: int = 600,
           exclude=None, plane=None, n_seeds: int = 3, max_points: int = 200_000) -> Candidate | None:
    """The best hidden-point candidate in the whitened residual ``R`` (n_ill, n_obs, n_bins).

    z, n, rho: visible positions, normals, albedos (in ``view.ids`` order); ``exclude``: points
    (K, 3) already modelled (candidates within 2 IRF widths are skipped); ``plane``: the unit
    normal of a plane through the source that holds every patch (the flatland prior).

    The strongest returns left in the residual seed the search: the point must lie on the
    spheroid of path lengths of such a return (foci the two visible patches of its trace), which
    is sampled every ``step`` and scored by T (each trace's matched filter dilated over the
    step), then the best points are refined by maximising the exact T."""
    grid = view.grid
    rows, cols = view.rows(), view.cols()
    n_ill, n_obs, nb = R.shape
    pi, pj = np.meshgrid(rows, cols, indexing="ij")
    pi, pj = pi.ravel(), pj.ravel()
    Rf = R.reshape(-1, nb)
    mf_all, e, _ = matched_filters(Rf, template, grid)
    zmf = mf_all / math.sqrt(e)
    peak = zmf.max(axis=1)
    if len(pi) > max_traces:  # the traces with the strongest residual returns
        keep = np.argsort(peak)[::-1][:max_traces]
        pi, pj, mf_all, peak = pi[keep], pj[keep], mf_all[keep], peak[keep]
    r = np.linalg.norm(z - view.source, axis=1)
    c = np.linalg.norm(z - view.camera, axis=1)
    if not view.capture.legs_included:
        r = np.zeros_like(r)
        c = np.zeros_like(c)
    W = template.width
    step = max(step, 1e-4)
    dil = max(int(math.ceil(2.0 * step / grid.bin_width)) | 1, 1)
    ctx = {"z": z, "n": n, "rho": np.clip(rho, 0.05, 1.0), "pi": pi, "pj": pj, "r": r, "c": c,
           "scale": 1.0 / math.pi ** 3, "t0": grid.start, "bw": grid.bin_width, "nb": nb, "mf": mf_all,
           "mfd": maximum_filter1d(mf_all, dil, axis=1) if dil > 1 else mf_all, "e": e}
    centres = grid.centres
    seeds = []
    for t in np.argsort(peak)[::-1]:
        k = int(np.argmax(mf_all[t]))
        ex = centres[k] - r[pi[t]] - c[pj[t]]
        if ex <= 0:
            continue
        seeds.append((t, ex))
        if len(seeds) >= n_seeds:
            break
    # coarse-to-fine: a late return's spheroid sampled at ``step`` can hold millions of points
    # (4.1 M in coverage-study seed 93: 100 s of the statistic). Past ``max_points`` the
    # spheroids are sampled at a coarser step (each matched filter dilated over it, so a peak
    # between nodes still scores), and the best coarse points are re-sampled at ``step``.
    area = sum(_spheroid_area(z[pi[t]], z[pj[t]], ex) for t, ex in seeds)
    n_fine = area / (step * step)
    coarse = step * max(1.0, math.sqrt(n_fine / max_points))
    pts = [_spheroid(z[pi[t]], z[pj[t]], ex, coarse) for t, ex in seeds]
    G = np.vstack(pts) if pts else np.zeros((0, 3))

    def admissible(P, band):
        if plane is not None and len(P):  # the flatland prior: points near the plane, projected onto it
            dpl = (P - view.source) @ plane
            P = P[np.abs(dpl) < band] - np.outer(dpl[np.abs(dpl) < band], plane)
        if len(P):
            v = P[:, None, :] - z[None]
            front = (np.einsum("gmd,md->gm", v, n) > 0).any(axis=1) & (np.linalg.norm(v, axis=2).min(axis=1) > 2 * W)
            P = P[front]
        if exclude is not None and len(exclude) and len(P):
            dex = np.linalg.norm(P[:, None, :] - np.asarray(exclude)[None], axis=2).min(axis=1)
            P = P[dex > 2 * W]
        return P

    G = admissible(G, coarse)
    if not len(G):
        return None
    chunk = max(1, int(2e7 // max(len(pi), 1)))

    def scored(P, c):
        return np.concatenate([_T(P[s_:s_ + chunk], c, dilated=True)[0] for s_ in range(0, len(P), chunk)])

    n_tested = int(len(G) * (coarse / step) ** 2)
    cur = coarse
    while cur > step * 1.01:
        # the best 40 points at this level, re-sampled on cubes of half-width ``cur`` at a step
        # a quarter as large (down to ``step``), each level's matched filters dilated over its step
        dil_c = max(int(math.ceil(2.0 * cur / grid.bin_width)) | 1, 1)
        ctx_c = dict(ctx, mfd=maximum_filter1d(mf_all, dil_c, axis=1) if dil_c > 1 else mf_all)
        Tc = scored(G, ctx_c)
        order = np.argsort(Tc)[::-1][:40]
        order = order[Tc[order] > 0]
        if not len(order):
            return None
        nxt = max(step, cur / 4.0)
        k_c = int(math.ceil(cur / nxt))
        ax = np.arange(-k_c, k_c + 1) * nxt
        cube = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)
        G = admissible((G[order][:, None, :] + cube[None]).reshape(-1, 3), 2.0 * cur)
        if not len(G):
            return None
        cur = nxt
    T = scored(G, ctx)
    if plane is not None:
        e1 = np.cross(plane, np.eye(3)[int(np.argmin(np.abs(plane)))])
        e1 /= np.linalg.norm(e1)
        basis = np.stack([e1, np.cross(plane, e1)], axis=1)
    else:
        basis = np.eye(3)
    d_in = basis.shape[1]
    best = []
    for g0 in np.argsort(T)[::-1][:3]:
        if T[g0] <= 0:
            continue
        fine = np.linspace(-step, step, 7)
        off = np.stack(np.meshgrid(*([fine] * d_in), indexing="ij"), axis=-1).reshape(-1, d_in)
        F = G[g0] + off @ basis.T
        Tf, _ = _T(F, ctx)
        x0 = F[int(np.argmax(Tf))]
        res = minimize(lambda p: -_T((x0 + basis @ p)[None], ctx)[0][0], np.zeros(d_in),
                       method="Nelder-Mead",
                       options={"xatol": 1e-3 * W, "fatol": 1e-3, "maxiter": 150,
                                "initial_simplex": np.vstack([np.zeros(d_in), 0.5 * W * np.eye(d_in)])})
        xb = x0 + basis @ res.x
        Tx, bx = _T(xb[None], ctx)
        best.append((float(Tx[0]), xb, float(bx[0])))
    if not best:
        return None
    Tb, xb, bb = max(best, key=lambda t: t[0])
    if Tb <= 0:
        return None
    f, _ = _weights(xb[None], z, n, ctx["rho"])
    cen = np.average(z, axis=0, weights=np.maximum(f[0], 1e-30))
    nrm = cen - xb
    return Candidate(xb, Tb, bb, nrm / np.linalg.norm(nrm), n_tested=int(max(n_tested, len(G))))
