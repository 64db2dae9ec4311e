"""Synthetic relay-wall twins rendered by the project's forward model (``transport.simulate``).

A planar wall z = 0 (normal +z) of n x n small Lambertian patches; the hidden scene is a set of
small patches at z > 0 declared hidden (the camera and the source never see them); the source
and camera sit in front of the wall, on the hidden side, as in a real relay-wall setup. The
STIR is simulated with ``legs_included=False`` (rectified, t = 0 at the wall), three bounces:
the only non-zero returns between distinct times are wall -> hidden -> wall. Confocal captures
keep the diagonal (i, i); paired captures keep chosen (laser, detector) pairs.
"""
from __future__ import annotations

import numpy as np

from stircasadi.brdf import Lambertian
from stircasadi.capture import Capture
from stircasadi.irf import GaussianIRF
from stircasadi.scene import Patch, Scene
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import simulate

WALL_RHO = 0.8


def surface_patches(depth_fn, half: float, n: int, rho=0.7, mask=None, normal_fn=None, cells: bool = False):
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


def letter_mask(rows, n_sub: int) -> np.ndarray:
    """A bitmap (list of strings, '#' = surface, first string = largest y) magnified so each
    character covers n_sub x n_sub patches; row 0 of the result is the smallest y."""
    bm = np.array([[c == "#" for c in r] for r in rows[::-1]])
    return np.kron(bm, np.ones((n_sub, n_sub), bool))


def twin_fit(cap, truth, half: float, n: int, gain: float | None = (WALL_RHO / np.pi) ** 2,
             sub: int = 3, gate: float = 0.2, **options):
    """Fit the twin's surface on n x n nodes whose cells tile [-half, half]^2 (the rendered
    support, so no cell straddles the object's edge) and compare with the truth at the nodes.

    Returns (SurfaceResult, metrics dict: depth errors, normal errors (deg), albedo errors and
    their std on the nodes that hold surface, and the off-support albedo)."""
    from stircasadi.nlos import VolumeSettings, backprojection, from_capture, lct
    from stircasadi.nlos.surface import SurfaceSettings, fit_surface
    from stircasadi.nlos.surface.grid import DepthGrid

    rl = from_capture(cap)
    if gain is not None:
        rl.gain[:] = gain
    vol = (lct if rl.confocal else backprojection)(rl, VolumeSettings(gate_m=gate, n_lateral=16))
    h = 2 * half / n
    e = (-half + h / 2, half - h / 2)
    st = SurfaceSettings(n_nodes=n, levels=1, extent=e + e, subsamples=sub, known_gain=gain is not None,
                         max_iter=40, **options)
    res = fit_surface(rl, vol.maps(), st, gate=gate)
    tg = DepthGrid(truth["x"], truth["y"], res.grid.frame)
    # truth per node: the cell's patches (the nodes' cells tile the truth's patch grid)
    k = len(truth["x"]) // n
    cell = lambda a: a.reshape(n, k, n, k, *a.shape[2:]).mean(axis=(1, 3))
    alb = cell(truth["albedo"])
    full = cell(truth["mask"].astype(float)) > 0.999
    zt = tg.resample(truth["depth"], res.grid).reshape(res.shape)
    nt = cell(truth["normal"])
    nt /= np.linalg.norm(nt, axis=-1, keepdims=True)
    err = res.depth - zt
    ang = np.degrees(np.arccos(np.clip(np.sum(res.normals * nt, axis=-1), -1, 1)))
    return res, {"on": full, "depth_err": err[full], "depth_std": res.depth_std[full],
                 "normal_deg": ang[full], "albedo_err": (res.albedo - alb)[full],
                 "albedo_std": res.albedo_std[full], "albedo_off": res.albedo[~full & (alb == 0)]}


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
        from stircasadi.irf import sampled
        irf = sampled(GaussianIRF(fwhm), grid.bin_width)
    return Capture(grid=grid, traces=tr, pairs=pairs, legs_included=False,
                   illuminated_xyz=lxyz, observed_xyz=dxyz, illuminated_ids=ids,
                   observed_ids=ids if same_ids else ids + n, irf=irf,
                   noise={"model": "gaussian", "sigma": sigma} if sigma > 0 else {"model": "none"})


#: the response measured on the Stanford 40 cm charts' direct return (``surface.direct``, 16 ps):
#: a Gaussian core and two slow tails, mode at t = 0
STANFORD_RESPONSE = ("gaussian", 0.0046, 0.0, ((0.0265, 0.405), (0.1003, 0.393)))


def stanford_twin(path, depth=0.400, side=0.25, tilt_deg=0.0, brdf="retroreflective", n=64,
                  half=0.2, n_bins=1400, direct=43000.0, third=2300.0, bg=0.4, seed=0,
                  response=STANFORD_RESPONSE, h_q=0.0025, sub=4):
    """A rectified confocal scan in the Stanford release's own .mat layout (``rect_data`` counts
    at 4 ps, ``width``), rendered independently of the surface fit by quadrature: n x n scan
    points over [-half, half]^2 of the wall z = 0; a square of side ``side`` at ``depth`` (tilted
    by ``tilt_deg`` about y), sampled every ``h_q`` m; each sample's confocal return (amplitude
    cos_L cos_X / d^2 dA for a retroreflector, its square for a Lambertian surface; delay 2 d)
    split linearly between the two nearest centres of sub-bins of 4 ps / ``sub`` (exact mean),
    convolved with the response's sub-bin integrals (mode at the path length); the wall's own
    return is the response at t = 0 (bins before t = 0 cut, as in the release) times ``direct``
    counts; ``third`` counts per trace under the square; a constant ``bg``; Poisson noise.
    Returns the noise-free rate (n*n, n_bins)."""
    from scipy.io import savemat
    from scipy.signal import fftconvolve

    from stircasadi.nlos.surface.direct import response_cdf
    from stircasadi.nlos.surface.response import Response

    resp = Response(*response)
    w = 4e-12 * 299792458.0
    h = w / sub
    nf = n_bins * sub
    m0 = resp.mode_offset()
    pad = int(8 * resp.sigma / h) + 4
    k = np.arange(-pad, nf)
    K = response_cdf(resp, (k + 0.5) * h + m0) - response_cdf(resp, (k - 0.5) * h + m0)
    lin = np.linspace(-half, half, n)
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    P = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], 1)
    g = np.arange(-side / 2 + h_q / 2, side / 2, h_q)
    gy, gx = np.meshgrid(g, g, indexing="ij")
    t = np.tan(np.radians(tilt_deg))
    X = np.stack([gx.ravel(), gy.ravel(), depth + t * gx.ravel()], 1)
    nX = np.array([t, 0.0, -1.0]) / np.hypot(1.0, t)
    dA = h_q * h_q * np.hypot(1.0, t)
    lam = np.zeros((n * n, n_bins))
    for p0 in range(0, n * n, 128):
        v = X[None] - P[p0:p0 + 128, None]
        d = np.linalg.norm(v, axis=-1)
        A = (v[..., 2] / d) * (-(v @ nX) / d) / d ** 2 * dA
        if brdf != "retroreflective":
            A = A * (v[..., 2] / d) * (-(v @ nX) / d) / d ** 2
        u = 2 * d / h - 0.5                        # in units of sub-bin centres
        lo = np.floor(u).astype(np.int64)
        a = 1.0 - (u - lo)
        rows = np.repeat(np.arange(v.shape[0]) * nf, X.shape[0]).reshape(lo.shape)
        hist = (np.bincount((rows + np.clip(lo, 0, nf - 1)).ravel(), (A * a).ravel(), v.shape[0] * nf)
                + np.bincount((rows + np.clip(lo + 1, 0, nf - 1)).ravel(), (A * (1 - a)).ravel(),
                              v.shape[0] * nf)).reshape(-1, nf)
        fine = fftconvolve(hist, K[None], axes=1)[:, pad:pad + nf]
        lam[p0:p0 + 128] = fine.reshape(-1, n_bins, sub).sum(axis=2)
    s = lam.sum(axis=1)
    lam *= third / np.median(s[s > 0.3 * s.max()])
    j = np.arange(nf + 1)
    lam += direct * np.diff(response_cdf(resp, j * h + m0)).reshape(n_bins, sub).sum(axis=1)[None] + bg
    y = np.random.default_rng(seed).poisson(lam)
    savemat(path, {"rect_data": y.reshape(n, n, n_bins).astype(np.uint16), "width": np.array([[half]])})
    return lam
