"""Hidden surfaces by analysis by synthesis: a depth map and albedo per node fitted to the full
third-bounce transient (CasADi + IPOPT), coarse to fine, with Fisher error bars.

When to use: after a volumetric reconstruction (its depth / albedo / mask maps initialise the
fit) on any relay: confocal or paired wall scans, or a full STIR's visible patches (Fig. 13).

Steps
-----
1. Initial surface: the volume's depth map inside its mask (the median masked depth outside),
   its albedo map, resampled on a grid over the mask's bounding box (``SurfaceSettings``).
2. Noise: the relay's sigma, Poisson weights 1 / max(y, 1) for counts, or a MAD estimate.
3. Gain: with an unknown relay gain (real scans) one global factor scales the model to the data
   at the initial surface; albedos are then relative (``albedo_relative``).
4. Per level (coarse to fine): IPOPT on the level's NLP (``solve.py``), re-centred while
   depths reach the allowed slack; then the Gauss-Newton matrix H = J^T W J; with
   ``prior="auto"`` the smoothness weight is the largest for which the linearised whitened
   chi^2 stays within max(chi2_min, dof) (1 + 2 sqrt(2 / dof)) (discrepancy principle), and
   the level is re-solved when the weight changed.
5. Fisher covariance (H + lam R)^-1 (R the prior's operator), std maps of depth, albedo and
   normal components (normals linearised through the depth gradients), inflated by
   sqrt(chi2/dof) when above 1; the mask keeps nodes whose albedo is ``mask_z`` std above 0.

Neglects what ``physics.py`` neglects; one background level for all bins; a Gaussian IRF.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ...errors import ReconstructionError
from ...progress import get_logger
from ..relay import Relay
from ..volume import Maps
from .grid import DepthGrid
from .model import SurfaceModel
from .result import SurfaceResult
from .settings import SurfaceSettings
from .lm import solve_lm
from .solve import solve_level

__all__ = ["fit_surface", "noise_weights"]

_log = get_logger("stircasadi.nlos.surface")


def noise_weights(y: np.ndarray, sigma, override: float | None = None) -> tuple[np.ndarray, str]:
    """Inverse variances of the bins (and where they came from)."""
    if override is not None:
        return np.full(y.shape, 1.0 / override ** 2), "settings.noise_sigma"
    if sigma is not None and np.all(np.asarray(sigma) > 0):
        return np.broadcast_to(1.0 / np.asarray(sigma, float) ** 2, y.shape).copy(), "relay sigma"
    if np.all(y >= 0) and np.allclose(y, np.round(y)) and y.max() > 1:
        return 1.0 / np.maximum(y, 1.0), "poisson (counts)"
    d = np.diff(y, axis=1).ravel()
    s = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
    s = max(s, 1e-6 * float(np.max(np.abs(y))), 1e-300)
    return np.full(y.shape, 1.0 / s ** 2), "MAD of first differences"


def _initial(maps: Maps, grid: DepthGrid):
    d = np.where(maps.mask, maps.depth, np.median(maps.depth[maps.mask]) if maps.mask.any()
                 else np.median(maps.depth))
    src = DepthGrid(maps.x, maps.y, maps.frame)
    z0 = src.resample(d, grid)
    a0 = src.resample(np.where(maps.mask, maps.albedo, 0.05 * maps.albedo.max()), grid)
    return z0, np.clip(a0, 0.0, None)


def _extent(maps: Maps, st: SurfaceSettings):
    if st.extent is not None:
        return st.extent
    m = maps.mask if maps.mask.any() else np.ones_like(maps.mask)
    iy, ix = np.nonzero(m)
    x0, x1 = maps.x[ix.min()], maps.x[ix.max()]
    y0, y1 = maps.y[iy.min()], maps.y[iy.max()]
    gx = max(st.margin * (x1 - x0), maps.x[1] - maps.x[0])
    gy = max(st.margin * (y1 - y0), maps.y[1] - maps.y[0])
    return (x0 - gx, x1 + gx, y0 - gy, y1 + gy)


def _sigma0(relay: Relay, st: SurfaceSettings) -> float:
    if st.sigma0 is not None:
        return float(st.sigma0)
    if relay.irf is not None and getattr(relay.irf, "sigma", 0) > 0:
        return float(relay.irf.sigma)
    return 1.5 * relay.grid.bin_width


def _window(relay: Relay, grid: DepthGrid, z0, slack, sig, gate):
    X, _, _ = grid.geometry(z0)
    d = (np.linalg.norm(relay.L[:, None] - X[None], axis=-1) + np.linalg.norm(relay.D[:, None] - X[None], axis=-1)
         + relay.leg[:, None])
    pad = 6 * 2 * sig + 2 * slack + 2 * relay.grid.bin_width
    lo = max(float(d.min()) - pad, gate if gate is not None else -np.inf)
    return relay.window(lo, float(d.max()) + pad)


def _choose_lambda(H, g, chi2, dof, R, z_sl, lam_now):
    """Discrepancy principle on the linearised problem at the current solution."""
    npar = H.shape[0]
    Rf = np.zeros_like(H)
    Rf[z_sl, z_sl] = R
    hz = float(np.trace(H[z_sl, z_sl])) / max(np.trace(R), 1e-300)
    cands = np.concatenate([[0.0], hz * np.logspace(-8, 2, 41)])
    ridge = 1e-10 * float(np.trace(H)) / npar + 1e-300
    out = []
    theta_prior_grad = None
    for lam in cands:
        A = H + lam * Rf + ridge * np.eye(npar)
        rhs = g + (lam - lam_now) * (theta_prior_grad if theta_prior_grad is not None else 0.0)
        try:
            dlt = -np.linalg.solve(A, rhs)
        except np.linalg.LinAlgError:
            continue
        out.append((lam, chi2 + 2 * g @ dlt + dlt @ H @ dlt))
    if not out:
        return lam_now, []
    c_min = min(c for _, c in out)
    target = max(c_min, dof) * (1 + 2 * math.sqrt(2.0 / max(dof, 1)))
    ok = [lam for lam, c in out if c <= target]
    return (max(ok) if ok else 0.0), out


def fit_surface(relay: Relay, init: Maps, settings: SurfaceSettings | None = None,
                gate: float | None = None) -> SurfaceResult:
    """Fit a depth-map surface with albedo to ``relay``'s traces, starting from ``init`` maps.

    Parameters
    ----------
    relay : the traces and visible geometry (``stircasadi.nlos.relay``).
    init : depth / albedo / mask maps of a volumetric reconstruction in ``relay.frame``.
    settings : ``SurfaceSettings``.
    gate : earliest path length to model (the wall's own return lies before it).

    Returns
    -------
    SurfaceResult (never raises on a non-converged solve: ``success`` is False and ``reasons``
    says why).
    """
    st = (settings or SurfaceSettings()).validate()
    t_start = time.perf_counter()
    if relay.n_traces < 4:
        raise ReconstructionError(f"A surface fit needs at least 4 traces; got {relay.n_traces}.")
    sig_c = _sigma0(relay, st)
    sig_first = sig_c
    w = relay.grid.bin_width
    slack = st.z_slack if st.z_slack is not None else (1.5 if st.solver == "lm" else 3.0) * w
    ext = _extent(init, st)
    sizes = [max(4, int(round(st.n_nodes / 2 ** (st.levels - 1 - k)))) for k in range(st.levels)]
    frame = relay.frame
    levels, reasons = [], []
    prev = None
    lam = 0.0 if st.prior in ("auto", "none") else float(st.prior)
    gain_scale = 1.0
    rl = relay
    for li, n in enumerate(sizes):
        grid = DepthGrid.square(frame, ext[:2], ext[2:], n)
        if prev is None:
            z, rho = _initial(init, grid)
        else:
            z, rho = prev[0].resample(prev[1], grid), np.clip(prev[0].resample(prev[2], grid), 0, None)
        h = math.sqrt(grid.hx * grid.hy)
        lap = grid.laplacian()
        R = (lap.T @ lap).toarray() / h ** 2
        rl = _window(relay, grid, z, slack, 2 * sig_c, gate)
        y = rl.traces
        wgt, noise_src = noise_weights(y, rl.sigma, st.noise_sigma)
        bg = float(np.median(y)) if noise_src.startswith("poisson") else 0.0
        if li == 0:
            model = SurfaceModel(grid, rl, z, 2 * sig_c, slack, st.chunk_pairs)
            m1 = model.predict(z, rho, sig_c, 0.0)
            s = float(np.sum(m1 * (y - bg)) / max(np.sum(m1 * m1), 1e-300))
            if not (s > 0):
                raise ReconstructionError("The initial surface predicts no signal where the data have "
                                          "it; check the relay geometry and the time window.")
            if st.known_gain:
                rho = np.clip(rho * s, 0.0, 1.0)
            else:
                gain_scale = s / max(float(rho.max()), 1e-12)
                rho = rho / max(float(rho.max()), 1e-12)
        rl.gain = rl.gain * gain_scale
        rho_max = 1.0 if st.known_gain else 1e3
        s_rho = max(float(np.max(rho)), 1e-3)
        s_b = max(float(np.sqrt(np.mean(1.0 / wgt))), 1e-300)
        info = {"nodes": n, "rows": int(y.size), "solves": []}
        sig_lo, sig_hi = sig_first / 3.0, 2.5 * sig_first
        last = li == len(sizes) - 1
        for rep in range(2 if (st.prior == "auto" and last) else 1):
            if st.solver == "lm":
                model = SurfaceModel(grid, rl, z, sig_hi, slack, st.chunk_pairs)
                res = solve_lm(model, y, wgt, z, rho, sig_c, bg, lam, lap, h, slack, rho_max,
                               st.fit_sigma, (sig_lo, sig_hi), st.max_iter, st.tol)
            else:
                for outer in range(st.outer):
                    model = SurfaceModel(grid, rl, z, 2 * sig_c, slack, st.chunk_pairs)
                    res = solve_level(model, y, wgt, z, rho, sig_c, bg, lam, lap, h, slack, rho_max,
                                      st.fit_sigma, st.max_iter, st.tol, s_rho, s_b)
                    moved = res["sigma"] != sig_c
                    z, rho, bg, sig_c = res["z"], res["rho"], res["bg"], res["sigma"]
                    if not (res["z_at_slack"] or (res["sigma_at_bound"] and moved)):
                        break
                model = SurfaceModel(grid, rl, res["z"], sig_hi, slack, st.chunk_pairs)
            z, rho, bg, sig_c = res["z"], res["rho"], res["bg"], res["sigma"]
            info["solves"].append({k: res[k] for k in ("status", "iterations", "success", "f")}
                                  | {"lam": lam, "sigma": sig_c})
            _log.info("level %d (%dx%d) solve: %s, %d it, f=%.4g, lam=%.3g, sigma=%.4g",
                      li, n, n, res["status"], res["iterations"], res["f"], lam, sig_c)
            H = model.gauss_newton(z, rho, sig_c, wgt, st.fit_sigma)
            m, e, grads = model.value_and_grad(z, rho, sig_c, bg, y=y, wgt=wgt)
            r = m - y
            chi2 = float(np.sum(wgt * r * r))
            npar = H.shape[0]
            dof = max(int(y.size) - npar, 1)
            gvec = np.concatenate([grads[0], grads[1]] + ([np.array([grads[2]])] if st.fit_sigma else [])
                                  + [np.array([grads[3]])])
            if st.prior != "auto" or not last:
                break
            new_lam, curve = _choose_lambda(H, gvec, chi2, dof, R, slice(0, grid.n), lam)
            info["lambda_curve"] = [(float(a), float(b)) for a, b in curve]
            if rep == 0 and (new_lam > 3 * lam or new_lam < lam / 3) and not (new_lam == 0 and lam == 0):
                lam = new_lam
                continue
            break
        info.update({"lam": lam, "chi2_dof": chi2 / dof, "status": res["status"], "success": res["success"]})
        levels.append(info)
        if not res["success"]:
            reasons.append(f"level {li} ({n}x{n}): IPOPT status {res['status']}")
        prev = (grid, z, rho)
    # ---- Fisher covariance at the finest level
    N = grid.n
    Rf = np.zeros_like(H)
    Rf[:N, :N] = R
    A = H + lam * Rf
    A += (1e-12 * float(np.trace(A)) / A.shape[0]) * np.eye(A.shape[0])
    C = np.linalg.inv(A)
    infl = max(1.0, chi2 / dof)
    Cz = C[:N, :N] * infl
    z_std = np.sqrt(np.maximum(np.diag(Cz), 0))
    rho_std = np.sqrt(np.maximum(np.diag(C[N:2 * N, N:2 * N]) * infl, 0))
    sig_std = math.sqrt(max(C[2 * N, 2 * N] * infl, 0)) if st.fit_sigma else None
    X, nrm, _ = grid.geometry(z)
    Gx, Gy = grid.gradient_ops()
    gx, gy = Gx @ z, Gy @ z
    GxC, GyC = np.asarray(Gx @ Cz), np.asarray(Gy @ Cz)
    vxx = np.sum(GxC * Gx.toarray(), axis=1)
    vyy = np.sum(GyC * Gy.toarray(), axis=1)
    vxy = np.sum(GxC * Gy.toarray(), axis=1)
    n_std = _normal_std(grid, gx, gy, vxx, vyy, vxy)
    mask = (rho > st.mask_z * rho_std) & (rho > 0.1 * max(float(rho.max()), 1e-300))
    shape = grid.shape
    success = not reasons
    if chi2 / dof > 1 + 5 * math.sqrt(2.0 / dof):
        reasons.append(f"whitened chi2/dof = {chi2 / dof:.3g} (the model leaves structure in the "
                       "residual; std inflated by sqrt(chi2/dof))")
    return SurfaceResult(
        grid=grid, depth=z.reshape(shape), albedo=rho.reshape(shape), normals=nrm.reshape(shape + (3,)),
        depth_std=z_std.reshape(shape), albedo_std=rho_std.reshape(shape),
        normal_std=n_std.reshape(shape + (3,)), mask=mask.reshape(shape), sigma_irf=float(sig_c),
        sigma_irf_std=sig_std, background=float(bg), gain=float(gain_scale), prior_weight=float(lam),
        prior_method={"auto": "discrepancy principle", "none": "none"}.get(st.prior, "fixed")
        if isinstance(st.prior, str) else "fixed",
        chi2_dof=float(chi2 / dof), dof=int(dof), albedo_relative=not st.known_gain,
        success=success, levels=levels, wall_time_s=time.perf_counter() - t_start, reasons=reasons,
        extras={"noise": noise_src, "window": [rl.grid.start, rl.grid.end], "n_traces": relay.n_traces,
                "residual_chi2_per_trace": (np.sum(wgt * r * r, axis=1)).tolist()
                if relay.n_traces <= 4096 else None})


def _normal_std(grid: DepthGrid, gx, gy, vxx, vyy, vxy) -> np.ndarray:
    """Std of the unit normal's components from the covariance of the depth gradients."""
    _, u, v, w = grid.frame
    s = np.sqrt(1 + gx ** 2 + gy ** 2)
    a = -(w[None] - gx[:, None] * u[None] - gy[:, None] * v[None])  # unnormalised normal
    # d(a/s)/dgx = u/s - a gx / s^3 ; d(a/s)/dgy = v/s - a gy / s^3
    dx = u[None] / s[:, None] - a * (gx / s ** 3)[:, None]
    dy = v[None] / s[:, None] - a * (gy / s ** 3)[:, None]
    var = dx ** 2 * vxx[:, None] + dy ** 2 * vyy[:, None] + 2 * dx * dy * vxy[:, None]
    return np.sqrt(np.maximum(var, 0))
