"""Relay-wall and confocal captures: hidden surfaces from onsets at known wall points.

When to use: paired or confocal traces with known wall points (``illuminated_xyz`` /
``observed_xyz``), typically rectified (``legs_included=False``): the onset of the first hidden
return of the pair (L, D) is t = min over hidden points X of |L - X| + |X - D| (confocal:
2 |X - P|).

Per trace, after a gate that skips the wall's own return, the first family's onset is fitted
with the *edge* model of onsets.py (an extended surface starts as a step blurred by the IRF;
a Gaussian IRF of ``irf_fwhm`` or, when not given, the width that fits the strongest traces
best). Then two nonlinear least-squares models (robust soft-L1 loss, scipy):

* point:  t_p = |L_p - X| + |X - D_p|                     (sphere / ellipsoid constraints)
* plane:  t_p = |mirror_plane(L_p) - D_p|  (= 2 dist(P, plane) when confocal; the earliest
  path to a plane reflects at it), plane n . x = delta.

The hidden-object depth (``extras['depth_m']``) is the fitted point's distance from the wall
plane; the plane's depth in front of the wall centre is ``extras['plane_depth_m']``. Neglects: multiple hidden objects (the earliest wins per trace), occlusion, traces
whose earliest return comes from an object edge (down-weighted by the robust loss).
"""
from __future__ import annotations

import math
import time

import numpy as np
from scipy.optimize import least_squares

from ..errors import GeometryError
from ..irf import FWHM_TO_SIGMA
from .onsets import GaussTemplate, fit_onsets

__all__ = ["relay_onsets", "fit_point", "fit_plane", "estimate_relay"]



def _wall_points(capture):
    if capture.traces is None:
        tr, pairs = capture.as_pairs()
    else:
        tr, pairs = capture.traces, capture.pairs
    if capture.illuminated_xyz is None or capture.observed_xyz is None:
        raise GeometryError("Relay-wall estimation needs the wall points: the capture has no "
                            "illuminated_xyz/observed_xyz. Import with a format that gives them "
                            "(stanford-lct, ccsocr, general-nlos) or set them on the Capture.")
    ill, obs = capture.ill_ids(), capture.obs_ids()
    li = {int(v): k for k, v in enumerate(ill)}
    oi = {int(v): k for k, v in enumerate(obs)}
    L = capture.illuminated_xyz[[li[int(p)] for p in pairs[:, 0]]]
    D = capture.observed_xyz[[oi[int(p)] for p in pairs[:, 1]]]
    return tr, L, D


def relay_onsets(capture, gate_m: float | None = None, irf_fwhm: float | None = None,
                 top_fraction: float = 0.25, k_sigma: float = 5.0, smooth_bins: int | None = None):
    """Onset of the first hidden return per trace (metres of path, legs removed).

    Returns dict with L, D (n,3), tau, tau_std, snr, used (bool: strong enough and fitted),
    fwhm (the IRF width used), gate."""
    tr, L, D = _wall_points(capture)
    g = capture.grid
    w = g.bin_width
    c = g.start + (np.arange(g.n_bins) + 0.5) * w
    resid = capture.extras.get("rectify_residual_m") if isinstance(capture.extras, dict) else None
    if gate_m is None:
        # skip the wall's own return: past the summed histogram's early peak and its decay to
        # within 2x of the late background level
        s = tr.sum(axis=0)
        k_peak = int(np.argmax(s[: max(len(s) // 3, 1)]))
        late = float(np.median(s[len(s) // 2:]))
        after = np.flatnonzero(s[k_peak:] < 2.0 * late + 5 * math.sqrt(max(late, 1.0)))
        k_gate = k_peak + (int(after[0]) if after.size else 0) + 2
        gate_m = float(c[min(k_gate, len(c) - 1)])
    sel = c >= gate_m
    Y = tr[:, sel]
    cg = c[sel]
    nsm = smooth_bins or max(1, int(round(0.01 / w)))
    from scipy.ndimage import uniform_filter1d
    sm = uniform_filter1d(Y, nsm, axis=1)
    bg = np.median(Y, axis=1)
    strength = sm.max(axis=1) - bg
    order = np.argsort(strength)[::-1]
    n_use = max(8, int(top_fraction * len(order)))
    use = np.zeros(len(Y), bool)
    use[order[:n_use]] = True
    # rough onset: first bin above half the smoothed peak over background
    half = bg[:, None] + 0.5 * (sm.max(axis=1) - bg)[:, None]
    k0 = np.argmax(sm >= half, axis=1)
    tau0 = cg[k0]
    grid_sel = type(g)(float(cg[0] - 0.5 * w), w, int(len(cg)))
    if irf_fwhm is None:
        best = None
        strong = order[: min(64, len(order))]
        for fw in np.linspace(2 * w, 40 * w, 20) if w < 0.005 else np.linspace(1.0 * w, 8 * w, 15):
            f = fit_onsets(Y[strong], grid_sel, GaussTemplate(fw * FWHM_TO_SIGMA, w), tau0[strong],
                           model="edge", poisson=True)
            cost = np.nanmedian(f.chi2)
            if best is None or cost < best[0]:
                best = (cost, fw)
        irf_fwhm = best[1]
    tm = GaussTemplate(irf_fwhm * FWHM_TO_SIGMA, w)
    fit = fit_onsets(Y[use], grid_sel, tm, tau0[use], model="edge", poisson=True)
    tau = np.full(len(Y), np.nan)
    std = np.full(len(Y), np.nan)
    snr = np.zeros(len(Y))
    idx = np.flatnonzero(use)
    ok = fit.found & np.isfinite(fit.tau_std) & (fit.tau > gate_m)
    tau[idx[ok]] = fit.tau[ok]
    std[idx[ok]] = fit.tau_std[ok]
    snr[idx] = fit.snr
    if resid is not None:
        tau = tau + np.asarray(resid, float)
    return {"L": L, "D": D, "tau": tau, "tau_std": std, "snr": snr, "used": np.isfinite(tau),
            "fwhm": float(irf_fwhm), "gate": float(gate_m)}


def fit_point(L, D, t, s, x0=None):
    """Hidden point X from |L - X| + |X - D| = t (robust NLS). Returns (X, cov, result)."""
    ok = np.isfinite(t) & np.isfinite(s)
    L, D, t, s = L[ok], D[ok], t[ok], np.maximum(s[ok], 1e-6)
    if x0 is None:
        n = _wall_normal(np.vstack([L, D]))
        x0 = np.vstack([L, D]).mean(axis=0) + n * float(np.median(t)) / 2

    def res(x):
        return (np.linalg.norm(L - x, axis=1) + np.linalg.norm(D - x, axis=1) - t) / s

    r = least_squares(res, x0, loss="soft_l1", f_scale=3.0)
    cov = np.linalg.pinv(r.jac.T @ r.jac)
    return r.x, cov, r


def _wall_normal(P):
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    n = vt[-1]
    return n if n[2] >= 0 else -n


def fit_plane(L, D, t, s):
    """Hidden plane n . x = delta from t = |mirror(L) - D| (robust NLS).

    Returns dict(normal, delta, depth, depth_std, wall_centre, wall_normal, result)."""
    ok = np.isfinite(t) & np.isfinite(s)
    L, D, t, s = L[ok], D[ok], t[ok], np.maximum(s[ok], 1e-6)
    if len(t) < 3:
        raise GeometryError(f"A hidden plane needs >= 3 traces with an onset; got {len(t)}.")
    P = np.vstack([L, D])
    wc = P.mean(axis=0)
    wn = _wall_normal(P)

    def unpack(p):
        th, ph, dep = p
        n = np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])
        n = n if n @ wn >= 0 else -n
        return n, float(n @ wc + dep)

    def res(p):
        n, delta = unpack(p)
        Lm = L - 2 * ((L @ n) - delta)[:, None] * n[None, :]
        return (np.linalg.norm(Lm - D, axis=1) - t) / s

    th0 = math.acos(np.clip(wn[2], -1, 1))
    ph0 = math.atan2(wn[1], wn[0])
    r = least_squares(res, [th0, ph0, float(np.median(t)) / 2], loss="soft_l1", f_scale=3.0,
                      x_scale=[0.1, 0.1, 0.1])
    cov = np.linalg.pinv(r.jac.T @ r.jac)
    n, delta = unpack(r.x)
    # depth: distance from the wall centre to the plane along the wall normal
    depth = float((delta - n @ wc) / (n @ wn))
    # robust scale: rescale the covariance by the median absolute normalised residual
    scale2 = float(np.median(np.abs(r.fun)) / 0.6745) ** 2
    return {"normal": n, "delta": delta, "depth": depth,
            "depth_std": float(math.sqrt(max(cov[2, 2] * scale2, 0.0))),
            "wall_centre": wc, "wall_normal": wn, "n_traces": int(len(t)), "result": r}


def estimate_relay(capture, gate_m: float | None = None, irf_fwhm: float | None = None,
                   level_z: float = 2.576):
    """The geometry stage for a relay-wall capture: onsets, hidden plane and hidden point."""
    from .result import GeometryEstimate, StageStats

    t0 = time.perf_counter()
    on = relay_onsets(capture, gate_m=gate_m, irf_fwhm=irf_fwhm)
    t1 = time.perf_counter()
    pl = fit_plane(on["L"], on["D"], on["tau"], on["tau_std"])
    X, cov, rp = fit_point(on["L"], on["D"], on["tau"], on["tau_std"])
    t2 = time.perf_counter()
    wn, wc = pl["wall_normal"], pl["wall_centre"]
    point_depth = float((X - wc) @ wn)
    ids_max = int(max(capture.ill_ids().max(), capture.obs_ids().max()))
    foot = pl["wall_centre"] + pl["depth"] * pl["wall_normal"]
    positions = np.vstack([foot, X])
    used = on["used"]
    hdb = [{"id": ids_max + 1, "kind": "plane foot (earliest return per trace)",
            "pairs": capture.pairs[used] if capture.pairs is not None else None,
            "distances": on["tau"][used] / 2, "eps": level_z * on["tau_std"][used] / 2}]
    amb = [{"kind": "extended-surface",
            "message": "a relay-wall capture of an extended object gives its earliest surface; "
                       "patch 1 is the hidden plane's foot point in front of the wall centre, "
                       "patch 2 the single point that best fits all onsets (sphere/ellipsoid "
                       "constraints)."}]
    est = GeometryEstimate(
        ids=[ids_max + 1, ids_max + 2], positions=positions, visible=[False, False],
        normals=np.vstack([pl["normal"], np.full(3, np.nan)]),
        position_std=np.vstack([np.abs(pl["wall_normal"]) * pl["depth_std"],
                                np.sqrt(np.maximum(np.diag(cov), 0))]),
        hidden_distance_bounds=hdb, frame="capture", ambiguities=amb,
        stats={"onsets": StageStats("onsets", "ok", 0, t1 - t0, True,
                                    {"n_traces": int(len(on["tau"])), "n_used": int(used.sum()),
                                     "irf_fwhm_m": on["fwhm"], "gate_m": on["gate"]}),
               "hidden_plane": StageStats("hidden_plane", str(pl["result"].message), int(pl["result"].nfev),
                                          t2 - t1, bool(pl["result"].success),
                                          {"depth_m": pl["depth"], "depth_std_m": pl["depth_std"]}),
               "hidden_point": StageStats("hidden_point", str(rp.message), int(rp.nfev), 0.0,
                                          bool(rp.success), {"depth_m": point_depth})},
        extras={"plane": {k: v for k, v in pl.items() if k != "result"}, "onsets": on,
                "depth_m": point_depth, "plane_depth_m": pl["depth"]})
    return est
