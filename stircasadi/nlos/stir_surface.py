"""Fig. 13: a hidden panel reconstructed from a full STIR with legs by the relay-wall surface route.

When to use: a full STIR (n_ill x n_obs x T, source and camera legs included) whose visible
patches are known (positions, normals, albedos, areas: from the joint visible fit, or a twin's
known relay) and whose hidden part is one surface seen only through third bounces
(``problems/three_planes_occluded``). :func:`hidden_surface_from_stir` never reads the
capture's ``truth``; :func:`compare_with_patches` takes the truth as an explicit argument.

Steps of :func:`hidden_surface_from_stir`
-----------------------------------------
1. Visible light removed by subtraction, not by a time gate: the STIR of the visible patches
   alone (with the occluders) is simulated by ``transport.simulate`` (three bounces, legs, the
   capture's impulse response) and subtracted. A gate cannot do it: on Fig. 13 the visible
   second bounces (about 400 noise std) overlap the start of the hidden third bounce in time.
   What is left is the hidden patches' third bounce i -> X -> j plus the noise (exact when the
   visible geometry is; the forward model has no fourth bounce).
2. The relay (``relay.from_stir``): L = illuminated patch, D = observed patch, legs
   |s - L| + |D - o|, gain f(L) f(D) = phi rho_L rho_D / pi^2 (the transport's convention: the
   aimed patch's radiance is rho_L / pi phi / a_L, its area cancels against the form factor's;
   the camera reads D's radiance, no area of D), noise std the capture's. Every ``ill_step``-th
   illumination and ``obs_step``-th observation are kept (cost ~ traces x nodes).
3. The frame (unless given): a coarse filtered backprojection over a world-aligned box (the
   relay points' bounding box grown by ``search_margin``), a weighted plane through its brightest
   voxels; ``w`` is that plane's normal pointing from the relay into the hidden scene, so the
   hidden surface is a height field over (u, v).
4. Filtered backprojection in that frame (lateral range: the bright voxels' extent grown by
   ``margin``): its depth / albedo / mask maps initialise ``fit_surface`` (known gain: the
   albedo is absolute, per unit area of the surface).

Status (measured on the twin, ``python -m stircasadi.nlos.stir_surface --noise 1e-8 --ill-step
12``: 882 traces, 6 x 6 coarse then 8 x 8 nodes, 10 LM iterations; BENCHMARKS.md): not yet a
reliable reconstruction. 109 s, 1.8 GB (2026-12-03); the final fit stops at its iteration limit with chi2/dof
2.03, 32 of the 49 patches inside its 19-node mask, depth errors median 9.7 mm (p90 6.0 cm),
normals 7.1 deg, |err|/std median 35: flagged (iteration limit, unexplained returns, chi2/dof).
The frame found is 13.6 deg off the panel's plane and its extent 1.6 x 1.2 m for a 0.56 m panel
(the coarse fit's mask spreads 0.4-0.7 m beyond the panel, in its plane); with the panel's own
plane given (diagnosis only) and 12 x 12 nodes over +-0.48 m the depth error median is 5.4 mm,
still flagged (chi2/dof 2.05: 49 point patches at 8 cm with random albedos against continuous
cells). At the problem's own 1e-6 (``--noise 1e-6 --ill-step 12``) the third bounce is ~1 noise
std per bin (total SNR ~98 over all 9604 traces): the fit's mask keeps 2 of 64 nodes, no
patch falls inside it (chi2/dof 1.0; 551 s, 3.7 GB).
Measured 2026-12-02 (``--noise 1e-6 --ill-step 10 --iter 15``, 356 s, 3.7 GB): 14 mask nodes,
chi2/dof 0.998, detection passed, no reason given, yet no patch inside the mask (nodes 0.6-2.4 m
from the panel): the fit's chi2 is over its own window only. The explained-returns check
(``surface.explained``) now fails that fit (residual matched-filter chi2 72 against 30.7, at
(-0.59, -0.44, 1.26) m, beside the panel); a frame from an oriented matched filter (the point's
normal searched over 200 directions) put the final fit's frame on the panel's plane, 16 deg off,
but the fit still missed (6 of 49 patches inside, 0.5 m off) and is flagged the same way.

At 1e-7 (``--noise 1e-7 --ill-step 12``, 2026-12-04, with step 4d's check in the coarse fit
too, since taken out of it: 600 s of its 800 s): 10 mask nodes, 23 of 49 patches inside, depth
error median 1.7 cm (p90 3.8 cm), normals 6.1 deg, |err|/std median 3.3, chi2/dof 1.01; flagged
by the final fit's iteration limit (its remaining step moves a mask node by 6.2 std).

Neglects: errors of the visible geometry (they leave second-bounce residuals), the occlusion of
relay-hidden legs by the occluders (``surface.physics``), the hidden-to-visible fourth bounce.
"""
from __future__ import annotations

import math
import resource
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import ReconstructionError
from .backprojection import backprojection
from .relay import Relay, from_stir
from .settings import VolumeSettings
from .surface import SurfaceResult, SurfaceSettings, fit_surface
from .surface.explained import matched_filter
from .volume import Maps, Volume

__all__ = ["VisiblePatches", "StirSurface", "hidden_surface_from_stir", "visible_stir",
           "third_bounce_relay", "compare_with_patches"]


@dataclass
class VisiblePatches:
    """The visible patches of a full STIR: ``ids`` (the capture's patch ids), positions (M, 3),
    unit normals (M, 3), Lambertian albedos (M,), areas (M,, m^2), and the scene's occluders
    (trimesh or None) that shadow their legs."""

    ids: np.ndarray
    positions: np.ndarray
    normals: np.ndarray
    albedos: np.ndarray
    areas: np.ndarray
    occluders: object = None

    @classmethod
    def from_scene(cls, scene) -> "VisiblePatches":
        """A twin's known relay: the scene's non-hidden patches (ids = their scene indices)."""
        ids = np.flatnonzero(~scene.hidden)
        return cls(ids, scene.positions[ids], scene.normals[ids], scene.albedos[ids], scene.areas[ids],
                   scene.occluders)

    def row(self, ids) -> np.ndarray:
        """Indices into these patches of the capture's patch ``ids`` (raises when one is absent)."""
        where = {int(v): k for k, v in enumerate(self.ids)}
        try:
            return np.array([where[int(i)] for i in ids], int)
        except KeyError as exc:
            raise ReconstructionError(f"The capture names patch id {exc} that the visible patches do not hold.") from exc


@dataclass
class StirSurface:
    """What :func:`hidden_surface_from_stir` returns."""

    surface: SurfaceResult
    relay: Relay
    volume: Volume
    maps: Maps
    frame: tuple
    stats: dict = field(default_factory=dict)


def visible_stir(capture, visible: VisiblePatches, irf=None) -> np.ndarray:
    """The visible patches' own STIR (first, second and visible third bounces, with legs and
    occluders) on the capture's rows, columns and grid."""
    from ..brdf import Lambertian
    from ..irf import from_samples
    from ..scene import Patch, Scene
    from ..sensor import Sensor
    from ..transport import simulate

    if irf is None:
        irf = from_samples(capture.irf, capture.grid.bin_width) if capture.irf is not None else None
    patches = [Patch(tuple(map(float, p)), tuple(map(float, n)), float(a), Lambertian(float(r)))
               for p, n, a, r in zip(visible.positions, visible.normals, visible.areas, visible.albedos)]
    scene = Scene(patches, source=capture.source_xyz, camera=capture.camera_xyz,
                  occluders=visible.occluders)
    tr = simulate(scene, capture.grid, Sensor(irf=irf) if irf is not None else Sensor(), bounces=3,
                  legs_included=True, allow_truncation=True)
    ri = {int(visible.ids[k]): r for r, k in enumerate(tr.ill_ids)}
    cj = {int(visible.ids[k]): c for c, k in enumerate(tr.obs_ids)}
    rows = np.array([ri.get(int(i), -1) for i in capture.ill_ids()])
    cols = np.array([cj.get(int(j), -1) for j in capture.obs_ids()])
    if (rows < 0).any() or (cols < 0).any():
        raise ReconstructionError("The visible patches' scene does not light / see every row / column "
                                  "of the capture (check their normals, the occluders, source and camera).")
    return tr.stir[np.ix_(rows, cols)]


def third_bounce_relay(capture, visible: VisiblePatches, ill_step: int = 1, obs_step: int = 1,
                       irf=None, phi: float = 1.0, frame=None) -> Relay:
    """The relay of the capture's hidden third bounce (steps 1 and 2 of the module docstring)."""
    from ..irf import from_samples

    if capture.stir is None or not capture.legs_included:
        raise ReconstructionError("hidden_surface_from_stir needs a full STIR with its legs.")
    if capture.source_xyz is None or capture.camera_xyz is None:
        raise ReconstructionError("A full STIR with legs needs source_xyz and camera_xyz to remove them.")
    if irf is None and capture.irf is not None:
        irf = from_samples(capture.irf, capture.grid.bin_width)
    resid = np.asarray(capture.stir, float) - visible_stir(capture, visible, irf)
    ii = np.arange(0, resid.shape[0], max(int(ill_step), 1))
    jj = np.arange(0, resid.shape[1], max(int(obs_step), 1))
    ri, cj = visible.row(capture.ill_ids()[ii]), visible.row(capture.obs_ids()[jj])
    alb = np.asarray(visible.albedos, float)
    gain = phi * np.outer(alb[ri], alb[cj]) / math.pi ** 2
    nz = capture.noise or {}
    sigma = float(np.asarray(nz["sigma"]).ravel()[0]) if str(nz.get("model", "")) == "gaussian" else None
    P = visible.positions
    rl = from_stir(resid[np.ix_(ii, jj)], capture.grid, P[ri], P[cj], visible.normals[ri],
                   visible.normals[cj], source_xyz=capture.source_xyz, camera_xyz=capture.camera_xyz,
                   gain=gain, sigma=sigma, irf=irf)
    if frame is not None:
        rl.frame = tuple(np.asarray(a, float) for a in frame)
    return rl


def _with_frame(relay: Relay, frame) -> Relay:
    return Relay(relay.traces, relay.grid, relay.L, relay.D, relay.nL, relay.nD, relay.leg,
                 relay.gain, relay.sigma, relay.irf, relay.confocal, frame, dict(relay.meta),
                 relay.footprint)


def matched_score(relay: Relay, X: np.ndarray, chunk: int = 64) -> np.ndarray:
    """Point-scatterer detection score of points ``X`` (K, 3) on the relay's own traces: with the
    relay weights a_p(X) = g_p max(cos_L, 0) max(cos_D, 0) / (|X - L|^2 |X - D|^2) (the hidden
    element's own cosines taken as 1) and y_p(t) the trace read at the path length (linear
    interpolation), score = (sum_p a_p y_p(t_p))^2 / (sum_p a_p^2 sigma^2): the chi^2 decrease of
    the best single point at X (a radiometrically weighted, normalised backprojection;
    ``surface.explained.matched_filter`` without a kernel)."""
    return matched_filter(relay, relay.traces, X, chunk=chunk)


def _find_frame(relay: Relay, margin: float, n: int, n_traces: int, top: float = 0.5):
    """Step 3: (frame, bright points (K, 3), weights): the matched score on a world box; the
    points scoring above ``top`` of the best, a weighted plane through them (w its normal, from
    the relay into the hidden scene)."""
    pts = np.vstack([relay.L, relay.D])
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    sub = relay.subset(np.unique(np.linspace(0, relay.n_traces - 1, min(n_traces, relay.n_traces)).astype(int)))
    ax = [np.linspace(lo[k], hi[k], n) for k in range(3)]
    G = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
    sc = matched_score(sub, G)
    keep = sc >= top * sc.max()
    X, wgt = G[keep], sc[keep]
    c = np.average(X, axis=0, weights=wgt)
    if len(X) >= 3:
        w = np.linalg.svd((X - c) * np.sqrt(wgt)[:, None], full_matrices=False)[2][-1]
    else:
        w = c - pts.mean(0)
    w = w / np.linalg.norm(w)
    if w @ (c - pts.mean(0)) < 0:
        w = -w
    ex = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ex - (ex @ w) * w
    u /= np.linalg.norm(u)
    return (c, u, np.cross(w, u), w), X, wgt


def _plane_frame(points, weights, towards):
    """(c, u, v, w) of the weighted plane through ``points``; w points away from ``towards``."""
    c = np.average(points, axis=0, weights=weights)
    w = np.linalg.svd((points - c) * np.sqrt(weights)[:, None], full_matrices=False)[2][-1]
    w = w if w @ (c - towards) > 0 else -w
    ex = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ex - (ex @ w) * w
    u /= np.linalg.norm(u)
    return c, u, np.cross(w, u), w


def _box(X, frame, margin):
    c, u, v, _ = frame
    a, b = (X - c) @ u, (X - c) @ v
    ga, gb = max(margin * np.ptp(a), 0.15), max(margin * np.ptp(b), 0.15)
    return a.min() - ga, a.max() + ga, b.min() - gb, b.max() + gb


def hidden_surface_from_stir(capture, visible: VisiblePatches, settings: SurfaceSettings | None = None,
                             ill_step: int = 8, obs_step: int = 1, frame=None, irf=None,
                             search_margin: float = 0.8, margin: float = 0.25, depth_pad: float = 0.3,
                             refine: bool = True, coarse_nodes: int = 6, coarse_iter: int = 8) -> StirSurface:
    """Reconstruct the hidden surface of a full-STIR ``capture`` from its third bounce off the
    ``visible`` patches (see the module docstring). ``settings``: the final fit's (default
    8 x 8 nodes, one level, known gain, 15 iterations). ``frame`` (c, u, v, w): a stated frame
    of the depth map (the surface must be a height field over it); else found (step 3). With
    ``refine`` a coarse fit (``coarse_nodes``, ``coarse_iter``) in that frame is followed by a
    weighted plane through its masked nodes: the final fit's frame is parallel to it and its
    extent the masked nodes' grown by ``margin`` (at least 0.15 m).

    Returns ``StirSurface`` (final surface fit, relay, initialising volume and maps, frame, and
    stats: wall times per stage, traces, the coarse fit, peak resident memory of the process)."""
    from dataclasses import replace

    t0 = time.perf_counter()
    rl = third_bounce_relay(capture, visible, ill_step, obs_step, irf)
    t1 = time.perf_counter()
    stats = {"traces": rl.n_traces, "ill_step": ill_step, "obs_step": obs_step, "subtract_s": t1 - t0}
    relay_mid = np.vstack([rl.L, rl.D]).mean(0)
    if frame is None:
        frame, X, _ = _find_frame(rl, search_margin, 32, 1500)
        x0, x1, y0, y1 = _box(X, frame, margin)
    else:
        frame = tuple(np.asarray(a, float) for a in frame)
        x0, x1, y0, y1 = -0.5, 0.5, -0.5, 0.5
    stats["frame_s"] = time.perf_counter() - t1
    c, u, v, w = frame
    # the depth map's origin sits depth_pad before the plane: BP depths are >= 0
    rl = _with_frame(rl, (c - depth_pad * w, u, v, w))
    t2 = time.perf_counter()
    vst = VolumeSettings(gate_m=0.0, n_lateral=24, xy_range=(x0, x1, y0, y1),
                         z_range=(0.0, 2 * depth_pad), n_depth=48, bp_filter="laplacian")
    vol = backprojection(rl, vst)
    maps = vol.maps()
    stats["backprojection_s"] = time.perf_counter() - t2
    st = settings or SurfaceSettings(n_nodes=8, levels=1, known_gain=True, max_iter=15, fit_sigma=False)
    if refine:
        t3 = time.perf_counter()
        coarse = fit_surface(rl, maps, replace(st, n_nodes=coarse_nodes, levels=1, max_iter=coarse_iter,
                                                subsamples=1, extent=None, explained=False,
                                                quadrature_check=False), gate=None)
        m = coarse.mask if coarse.mask.sum() >= 4 else coarse.albedo >= 0.5 * coarse.albedo.max()
        Xc = coarse.points()[m]
        fr2 = _plane_frame(Xc, coarse.albedo[m], relay_mid)
        ext = _box(Xc, fr2, margin)
        c2, u2, v2, w2 = fr2
        rl = _with_frame(rl, (c2 - depth_pad * w2, u2, v2, w2))
        xs, ys = np.linspace(ext[0], ext[1], 12), np.linspace(ext[2], ext[3], 12)
        maps = Maps(np.full((12, 12), depth_pad), np.ones((12, 12)), np.ones((12, 12), bool), xs, ys,
                    rl.frame)
        st = replace(st, extent=ext)
        stats["coarse"] = {"wall_time_s": time.perf_counter() - t3, "mask_nodes": int(coarse.mask.sum()),
                           "chi2_dof": coarse.chi2_dof, "status": coarse.levels[-1]["status"]}
    t4 = time.perf_counter()
    surf = fit_surface(rl, maps, st, gate=None)
    stats["surface_s"] = time.perf_counter() - t4
    stats["total_s"] = time.perf_counter() - t0
    stats["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return StirSurface(surf, rl, vol, maps, rl.frame, stats)


def compare_with_patches(surface: SurfaceResult, positions, normals) -> dict:
    """The surface against true patches (``positions``, ``normals`` (K, 3), given explicitly):
    for each patch, the surface's depth, normal and std bilinearly interpolated at the patch's
    (u, v) column; a patch counts as inside the mask when the node nearest its column is.

    Returns arrays per patch: ``inside`` (bool), ``depth_err`` (m, along w), ``depth_std``,
    ``z_score`` (|err| / std), ``normal_deg`` (angle to the true normal), ``normal_std_deg``
    (the normal std maps' norm, degrees), and ``lateral_out`` (columns outside the grid)."""
    from scipy.interpolate import RegularGridInterpolator

    g = surface.grid
    c, u, v, w = g.frame
    P = np.asarray(positions, float)
    Nt = np.asarray(normals, float)
    a, b, d = (P - c) @ u, (P - c) @ v, (P - c) @ w
    out_of = (a < g.x[0]) | (a > g.x[-1]) | (b < g.y[0]) | (b > g.y[-1])
    q = np.stack([np.clip(b, g.y[0], g.y[-1]), np.clip(a, g.x[0], g.x[-1])], 1)

    def at(m):
        return RegularGridInterpolator((g.y, g.x), m)(q)

    depth, dstd = at(surface.depth), at(surface.depth_std)
    nrm = np.stack([at(surface.normals[..., k]) for k in range(3)], 1)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    nstd = np.sqrt(sum(at(surface.normal_std[..., k]) ** 2 for k in range(3)))
    ix = np.clip(np.rint((a - g.x[0]) / g.hx).astype(int), 0, len(g.x) - 1)
    iy = np.clip(np.rint((b - g.y[0]) / g.hy).astype(int), 0, len(g.y) - 1)
    err = depth - d
    return {"inside": surface.mask[iy, ix] & ~out_of, "depth_err": err, "depth_std": dstd,
            "z_score": np.abs(err) / np.maximum(dstd, 1e-300),
            "normal_deg": np.degrees(np.arccos(np.clip(np.sum(nrm * Nt, axis=1), -1, 1))),
            "normal_std_deg": np.degrees(nstd), "lateral_out": out_of}


def _main(argv=None) -> None:
    """Twin study (known relay: the scene's visible patches): ``python -m
    stircasadi.nlos.stir_surface --noise 1e-8 --ill-step 12``. Truth is read here only, to compare."""
    import argparse

    from ..problems import three_planes_occluded as P
    from ..problems._common import paper_sensor
    from ..transport import simulate

    ap = argparse.ArgumentParser()
    ap.add_argument("--noise", type=float, default=1e-6)
    ap.add_argument("--ill-step", type=int, default=12)
    ap.add_argument("--nodes", type=int, default=8)
    ap.add_argument("--iter", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    sc, sen = P.build_scene(), paper_sensor(a.noise)
    cap = sen.capture(simulate(sc, P.build_grid(), sensor=sen), seed=a.seed)
    st = SurfaceSettings(n_nodes=a.nodes, levels=1, known_gain=True, max_iter=a.iter, fit_sigma=False)
    r = hidden_surface_from_stir(cap, VisiblePatches.from_scene(sc), st, ill_step=a.ill_step)
    s, hid = r.surface, sc.hidden
    m = compare_with_patches(s, sc.positions[hid], sc.normals[hid])
    ins = m["inside"]
    print(f"noise {a.noise:g}, traces {r.relay.n_traces}, nodes {s.shape}, mask {int(s.mask.sum())}, "
          f"chi2/dof {s.chi2_dof:.3g}, reasons {s.reasons}")
    print("stats", {k: (round(v, 2) if isinstance(v, float) else v) for k, v in r.stats.items()})
    print(f"patches inside the mask {int(ins.sum())} of {len(ins)}")
    if ins.any():
        for k in ("depth_err", "depth_std", "z_score", "normal_deg", "normal_std_deg"):
            q = np.abs(m[k][ins])
            print(f"{k}: median {np.median(q):.4g}, p90 {np.percentile(q, 90):.4g}")
        print(f"fraction |err|/std <= 2: {np.mean(m['z_score'][ins] <= 2):.3f}")


if __name__ == "__main__":
    _main()
