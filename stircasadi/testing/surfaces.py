"""Relay-wall twins rendered by the project's forward model (``transport.simulate``), and a
seeded generator of random hidden surfaces to judge the surface fit on scenes no one tuned it on.

A planar wall z = 0 (normal +z) of n x n small Lambertian patches; the hidden scene is a set of
small patches at z > 0 declared hidden (the camera and the source never see them); the source
and camera sit in front of the wall, on the hidden side, as in a real relay-wall setup. The
STIR is simulated with ``legs_included=False`` (rectified, t = 0 at the wall), three bounces:
the only non-zero returns between distinct times are wall -> hidden -> wall. Confocal captures
keep the diagonal (i, i); paired captures keep chosen (laser, detector) pairs.

:func:`random_surface_twin` draws one scene from a seed (shape, depth, tilt, size, albedo,
relay, noise) and :func:`score_surface` scores a fit against its truth (the truth is returned
beside the capture, never inside it); ``benchmarks/surface_coverage.py`` runs the study.
"""
from __future__ import annotations

import numpy as np

from ..brdf import Lambertian
from ..capture import Capture
from ..irf import GaussianIRF
from ..scene import Patch, Scene
from ..sensor import Sensor
from ..timegrid import TimeGrid
from ..transport import simulate

__all__ = ["WALL_RHO", "surface_patches", "wall_patches", "render", "confocal_capture", "paired_capture",
           "TWIN_KINDS", "random_surface_twin", "score_surface"]

WALL_RHO = 0.8


def surface_patches(depth_fn, half: float, n: int, rho=0.7, mask=None, cells: bool = False):
    """Hidden patches on z = depth_fn(x, y) over [-half, half]^2, n x n nodes, facing the wall.
    With ``cells`` the patches sit at the centres of n x n cells tiling the square (a continuous
    surface of exactly that support), else on its corners' grid.

    Returns (patches, truth dict with positions, normals, areas, albedo, (n, n) grids)."""
    lin = (np.linspace(-half, half, n + 1)[:-1] + half / n) if cells else np.linspace(-half, half, n)
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    zz = depth_fn(xx, yy)
    h = lin[1] - lin[0]
    gy, gx = np.gradient(zz, h, h)
    nrm = np.stack([gx, gy, -np.ones_like(zz)], axis=-1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    rho_map = np.broadcast_to(np.asarray(rho, float), zz.shape)
    area = h * h * np.sqrt(1 + gx ** 2 + gy ** 2)
    keep = np.ones_like(zz, bool) if mask is None else np.asarray(mask, bool)
    patches = []
    for iy in range(n):
        for ix in range(n):
            if keep[iy, ix] and rho_map[iy, ix] > 0:
                patches.append(Patch((xx[iy, ix], yy[iy, ix], zz[iy, ix]), tuple(nrm[iy, ix]),
                                     float(area[iy, ix]), Lambertian(float(rho_map[iy, ix])), hidden=True))
    truth = {"x": lin, "y": lin, "depth": zz, "normal": nrm, "albedo": np.where(keep, rho_map, 0.0),
             "mask": keep & (rho_map > 0), "area": area}
    return patches, truth


def wall_patches(n: int, half: float):
    lin = np.linspace(-half, half, n)
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    a = (2 * half / (n - 1)) ** 2 * 0.25
    return [Patch((float(x), float(y), 0.0), (0.0, 0.0, 1.0), a, Lambertian(WALL_RHO))
            for x, y in zip(xx.ravel(), yy.ravel())]


def render(n_wall: int, half: float, hidden: list, bin_width=0.005, n_bins=360, fwhm=0.012,
           source=(0.0, -0.9, 0.6)):
    """Full rectified STIR (n_wall^2, n_wall^2, n_bins) of wall + hidden patches."""
    wall = wall_patches(n_wall, half)
    scene = Scene(wall + list(hidden), source=source)
    grid = TimeGrid(0.0, bin_width, n_bins)
    tr = simulate(scene, grid, Sensor(irf=GaussianIRF(fwhm)), method="bounces", bounces=3,
                  legs_included=False, allow_truncation=True)
    xyz = scene.positions[: n_wall * n_wall]
    return tr.stir, grid, xyz


def confocal_capture(stir, grid, xyz, noise_rel=0.0, seed=0, fwhm=None):
    """Diagonal of the STIR as a confocal capture, with Gaussian noise of ``noise_rel`` x the
    largest hidden return (the first bounce at t = 0 is dropped by the estimators' gate)."""
    n = stir.shape[0]
    tr = stir[np.arange(n), np.arange(n)].copy()
    return _capture(tr, np.stack([np.arange(n)] * 2, 1), grid, xyz, xyz, noise_rel, seed, fwhm,
                    same_ids=True)


def paired_capture(stir, grid, xyz, laser_rows, noise_rel=0.0, seed=0, fwhm=None):
    """Traces (laser l, every detector) for l in ``laser_rows``: a non-confocal capture."""
    n = stir.shape[0]
    li, dj = np.meshgrid(np.asarray(laser_rows), np.arange(n), indexing="ij")
    li, dj = li.ravel(), dj.ravel()
    keep = li != dj
    li, dj = li[keep], dj[keep]
    tr = stir[li, dj].copy()
    ids = np.arange(n)
    return _capture(tr, np.stack([li, dj + n], 1), grid, xyz, xyz, noise_rel, seed, fwhm,
                    same_ids=False, ids=ids)


def _capture(tr, pairs, grid, lxyz, dxyz, noise_rel, seed, fwhm, same_ids, ids=None):
    gate = grid.centres > 0.1
    peak = float(np.max(np.abs(tr[:, gate]))) if gate.any() else 1.0
    sigma = noise_rel * peak
    if sigma > 0:
        tr = tr + np.random.default_rng(seed).normal(0.0, sigma, tr.shape)
    n = len(lxyz)
    ids = np.arange(n)
    irf = None
    if fwhm is not None:
        from ..irf import sampled
        irf = sampled(GaussianIRF(fwhm), grid.bin_width)
    return Capture(grid=grid, traces=tr, pairs=pairs, legs_included=False,
                   illuminated_xyz=lxyz, observed_xyz=dxyz, illuminated_ids=ids,
                   observed_ids=ids if same_ids else ids + n, irf=irf,
                   noise={"model": "gaussian", "sigma": sigma} if sigma > 0 else {"model": "none"})


# ------------------------------------------------------------------ seeded hidden-surface twins
#: shapes of ``random_surface_twin``
TWIN_KINDS = ("square", "disk", "letter", "cap", "two")


def random_surface_twin(seed: int, half: float = 0.15, n_patch: int = 30, n_wall: int = 8,
                        wall_half: float = 0.3, fwhm: float = 0.03, noise: float | None = None):
    """A seeded random hidden surface behind the relay wall, drawn from ``seed`` alone:
    ``kind`` one of TWIN_KINDS (a square or a disk on a tilted plane, an L-shaped letter, a
    spherical cap, two squares at two depths), depth 0.28-0.5 m, tilt 0-30 deg about a random
    axis, size 0.09-0.15 m, offset up to 4 cm, albedo 0.3-0.9, relay confocal or paired (4
    lasers), noise 0.3-3 % of the largest hidden return. Rendered by ``transport.simulate`` (1 cm
    Lambertian patches over [-half, half]^2, three bounces, Gaussian response of ``fwhm``).

    ``noise``: this relative noise level instead of the drawn one (the same scene and noise
    seed otherwise: twin experiments at another noise).

    Returns (capture, truth, description): truth holds ``depth_fn(x, y)`` and ``support_fn(x,
    y)`` (world x, y on the wall, z = depth; the support as rendered, patch by patch), ``albedo``
    and ``kind`` -- for scoring only."""
    rng = np.random.default_rng(seed)
    kind = TWIN_KINDS[int(rng.integers(len(TWIN_KINDS)))]
    relay = "confocal" if rng.random() < 0.5 else "paired"
    d0 = float(rng.uniform(0.28, 0.5))
    tilt = np.radians(rng.uniform(0.0, 30.0))
    az = rng.uniform(0.0, 2 * np.pi)
    gx, gy = np.tan(tilt) * np.cos(az), np.tan(tilt) * np.sin(az)
    s = float(rng.uniform(0.09, 0.15))
    cx, cy = rng.uniform(-0.04, 0.04, 2)
    rho = float(rng.uniform(0.3, 0.9))
    drawn = float(10 ** rng.uniform(np.log10(0.003), np.log10(0.03)))      # drawn in any case
    noise = drawn if noise is None else float(noise)
    lim = half - 1e-9

    def inside(x, y, a):          # the square |x|, |y| <= a about (cx, cy), inside the rendered square
        return (np.abs(x - cx) <= a) & (np.abs(y - cy) <= a) & (np.abs(x) <= lim) & (np.abs(y) <= lim)

    if kind == "square":
        def depth_fn(x, y): return d0 + gx * (x - cx) + gy * (y - cy)
        def support_fn(x, y): return inside(x, y, s)
    elif kind == "disk":
        def depth_fn(x, y): return d0 + gx * (x - cx) + gy * (y - cy)
        def support_fn(x, y): return ((x - cx) ** 2 + (y - cy) ** 2 <= s * s) & inside(x, y, half)
    elif kind == "letter":                                       # an L: two bars of width s / 1.6
        b = s / 1.6

        def depth_fn(x, y): return d0 + gx * (x - cx) + gy * (y - cy)

        def support_fn(x, y):
            u, v = x - cx, y - cy
            return inside(x, y, s) & ((u <= -s + b) | (v <= -s + b))
    elif kind == "cap":                                          # sphere of radius R, bulging to the wall
        R = float(rng.uniform(0.3, 0.8))

        def depth_fn(x, y): return d0 + R - np.sqrt(np.maximum(R * R - (x - cx) ** 2 - (y - cy) ** 2, 0.0))
        def support_fn(x, y): return ((x - cx) ** 2 + (y - cy) ** 2 <= s * s) & inside(x, y, half)
    else:       # two bars side by side, 8-15 cm apart in depth, a gap of >= 2.5 cm between them
        dd = float(rng.uniform(0.08, 0.15))     # (so no rendered patch's normal sees the step)
        a = s / 2.8

        def depth_fn(x, y): return np.where(x < cx, d0, d0 + dd) + 0.0 * y
        def support_fn(x, y):
            return inside(x, y, s) & (np.abs(np.abs(x - cx) - s / 2) <= a) & (np.abs(y - cy) <= s - 0.02)
    lin = np.linspace(-half, half, n_patch + 1)[:-1] + half / n_patch
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    hid, _ = surface_patches(depth_fn, half, n_patch, rho=rho, mask=support_fn(xx, yy), cells=True)
    hp = lin[1] - lin[0]

    def rendered(x, y):    # the support as rendered: the point's patch (1 cm square) is drawn
        x, y = np.asarray(x, float), np.asarray(y, float)
        ix, iy = np.rint((x - lin[0]) / hp), np.rint((y - lin[0]) / hp)
        ok = (ix >= 0) & (ix < n_patch) & (iy >= 0) & (iy < n_patch)
        return ok & support_fn(lin[0] + np.clip(ix, 0, n_patch - 1) * hp, lin[0] + np.clip(iy, 0, n_patch - 1) * hp)

    path_max = 2.0 * float(np.hypot(np.max(depth_fn(xx, yy)) + 0.05, wall_half + half)) + 0.2
    stir, grid, xyz = render(n_wall, wall_half, hid, n_bins=int(np.ceil(path_max / 0.01)), bin_width=0.01,
                             fwhm=fwhm)
    if relay == "confocal":
        cap = confocal_capture(stir, grid, xyz, noise_rel=noise, seed=seed, fwhm=fwhm)
    else:
        cap = paired_capture(stir, grid, xyz, [0, n_wall - 1, n_wall * (n_wall - 1), n_wall * n_wall - 1],
                             noise_rel=noise, seed=seed, fwhm=fwhm)
    shape = (f"tilt {np.degrees(tilt):.1f} deg" if kind in ("square", "disk", "letter")
             else f"radius {R:.2f} m" if kind == "cap" else f"step {dd:.3f} m")
    desc = (f"seed {seed}: {kind}, {relay}, depth {d0:.3f} m, {shape}, size {s:.3f} m, albedo {rho:.2f}, "
            f"noise {noise:.3g}")
    return cap, {"depth_fn": depth_fn, "support_fn": rendered, "albedo": rho, "kind": kind,
                 "relay": relay, "noise": noise}, desc


def score_surface(res, truth, q: int = 12, maps: bool = False) -> dict:
    """A surface fit against a ``random_surface_twin``'s truth, on the nodes whose whole cell
    (q x q sub-points) lies on the support with no depth step inside (the "full" nodes): depth,
    normal and albedo errors (MAE over the full nodes; ``depth_bias`` the mean signed depth error), the coverage
    (|err| / std < 2) of the depths and albedos of the full nodes the fit does not mark as ``edge``
    (``coverage2``, ``beyond2``, ``beyond4``, ``n_numbers``) and of those it marks
    (``edge_coverage2``, ``edge_beyond4``; the study's claims are both, ``surface_coverage.claims``),
    and the mask against the support; with ``maps`` also the (n, n)
    maps ``full``, ``depth_z``, ``albedo_z`` (error / std) and ``depth_err``."""
    g = res.grid
    c, u, v, w = (np.asarray(a, float) for a in g.frame)
    if abs(w @ np.array([0.0, 0.0, 1.0])) < 0.999:
        raise ValueError("score_surface expects the wall's frame (w along +z)")
    yy, xx = np.meshgrid(g.y, g.x, indexing="ij")
    off = (np.arange(q) + 0.5) / q - 0.5
    full = np.ones(xx.shape, bool)
    any_on = np.zeros(xx.shape, bool)
    zc = np.full(xx.shape, np.nan)
    for iy in range(xx.shape[0]):
        for ix in range(xx.shape[1]):
            P = c + xx[iy, ix] * u + yy[iy, ix] * v
            sx, sy = np.meshgrid(P[0] + off * g.hx, P[1] + off * g.hy)
            on = truth["support_fn"](sx, sy)
            zs = truth["depth_fn"](sx, sy)
            full[iy, ix] = on.all() and np.ptp(zs) < 0.5 * (g.hx + g.hy)   # no step inside the cell
            any_on[iy, ix] = on.any()
            zc[iy, ix] = float(truth["depth_fn"](np.array(P[0]), np.array(P[1]))) - c[2]
    e = 1e-4
    X = c[0] + xx * u[0] + yy * v[0]
    Y = c[1] + xx * u[1] + yy * v[1]
    dzx = (truth["depth_fn"](X + e, Y) - truth["depth_fn"](X - e, Y)) / (2 * e)
    dzy = (truth["depth_fn"](X, Y + e) - truth["depth_fn"](X, Y - e)) / (2 * e)
    nt = np.stack([dzx, dzy, -np.ones_like(dzx)], -1)
    nt /= np.linalg.norm(nt, axis=-1, keepdims=True)
    edge = res.edge

    err_d, err_a = res.depth - zc, res.albedo - truth["albedo"]
    z_d = err_d / np.maximum(res.depth_std, 1e-300)         # errors in std, per node
    z_a = err_a / np.maximum(res.albedo_std, 1e-300)

    def ratios(sel):
        return np.abs(np.concatenate([z_d[sel], z_a[sel]]))

    dz, da = err_d[full], err_a[full]
    inner = full & ~edge                # the claims: full nodes the fit does not mark as edge
    ratio, r_edge = ratios(inner), ratios(full & edge)
    ang = np.degrees(np.arccos(np.clip(np.sum(res.normals * nt, axis=-1), -1, 1)))[full]
    m = res.mask
    extra = {}
    if maps:     # per node: the full-cell mask and the errors in std (NaN off the full nodes)
        extra = {"full": full, "depth_z": np.where(full, z_d, np.nan), "albedo_z": np.where(full, z_a, np.nan),
                 "depth_err": np.where(full, err_d, np.nan)}
    return extra | {"n_full": int(full.sum()), "depth_mae": float(np.mean(np.abs(dz))) if full.any() else None,
            "depth_bias": float(np.mean(dz)) if full.any() else None,
            "normal_deg_median": float(np.median(ang)) if full.any() else None,
            "albedo_mae": float(np.mean(np.abs(da))) if full.any() else None,
            "n_inner": int(inner.sum()),
            "coverage2": float(np.mean(ratio < 2.0)) if ratio.size else None,
            "beyond2": int(np.sum(ratio >= 2.0)), "beyond4": int(np.sum(ratio > 4.0)), "n_numbers": int(ratio.size),
            "edge_coverage2": float(np.mean(r_edge < 2.0)) if r_edge.size else None,
            "edge_beyond4": int(np.sum(r_edge > 4.0)),
            "full_in_mask": float(np.mean(m[full])) if full.any() else None,
            "mask_off_support": int(np.sum(m & ~any_on)), "mask_nodes": int(m.sum())}
