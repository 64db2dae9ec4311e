"""Relay-wall twins for the tests: the renderers and the seeded surface generator live in
``stircasadi.testing.surfaces`` (re-exported here); this module adds the letter bitmaps, the
fixed-extent fit of a twin, and a twin of the Stanford release rendered by quadrature."""
from __future__ import annotations

import numpy as np

from stircasadi.testing.surfaces import (TWIN_KINDS, WALL_RHO, confocal_capture, paired_capture,  # noqa: F401
                                         random_surface_twin, render, score_surface, surface_patches,
                                         wall_patches)


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
    si, sj = np.meshgrid(lin, lin, indexing="ij")
    P = np.stack([si.ravel(), -sj.ravel(), np.zeros(n * n)], 1)     # the importer's axes
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


def linearise_against_fd(model, st, rng, shape):
    """``model.linearise`` (float64) at ``st`` on noisy data drawn from ``rng`` (the model plus
    1e-3 noise, weights in [0.5, 2], ``shape`` (traces, bins)) against central differences of
    ``predict`` (step 1e-6 of each unknown, at least 1e-9): asserts g = J^T W r and H = J^T W J
    agree, and returns (the linearisation, the finite-difference H)."""
    y = model.predict(st) + 1e-3 * rng.standard_normal(shape)
    wgt = rng.uniform(0.5, 2, shape)
    lin = model.linearise(st, y, wgt, dtype=np.float64)
    th = model.pack(st)
    J = np.zeros((y.size, model.npar))
    for i in range(model.npar):
        h = 1e-6 * max(abs(th[i]), 1e-3)
        tp, tm = th.copy(), th.copy()
        tp[i] += h
        tm[i] -= h
        J[:, i] = ((model.predict(model.unpack(tp, st)) - model.predict(model.unpack(tm, st))) / (2 * h)).ravel()
    r = (lin["m"] - y).ravel()
    g_fd = J.T @ (wgt.ravel() * r)
    H_fd = J.T @ (wgt.ravel()[:, None] * J)
    assert np.allclose(lin["g"], g_fd, rtol=1e-4, atol=1e-5 * np.abs(g_fd).max())
    assert np.allclose(lin["H"], H_fd, rtol=1e-5, atol=1e-8 * np.abs(H_fd).max())
    return lin, H_fd
