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
                 relay.gain, relay.sigma, relay.irf, relay.confocal, frame, dict(relay.meta))


def _find_frame(relay: Relay, margin: float, n: int, n_traces: int, top: float = 0.7):
    """Step 3: (frame, bright points (K, 3), weights) from a coarse backprojection in a world box:
    ``w`` points from the relay's centroid to the brightest voxels' centroid."""
    pts = np.vstack([relay.L, relay.D])
    lo, hi = pts.min(0) - margin, pts.max(0) + margin
    sub = relay.subset(np.unique(np.linspace(0, relay.n_traces - 1, min(n_traces, relay.n_traces)).astype(int)))
    rl = _with_frame(sub, (lo, *np.eye(3)))
    span = hi - lo
    vst = VolumeSettings(gate_m=0.0, n_lateral=n, xy_range=(0.0, span[0], 0.0, span[1]),
                         z_range=(0.0, span[2]), n_depth=n, bp_filter="none")
    vol = backprojection(rl, vst)
    v = np.asarray(vol.vol, float)
    keep = v >= top * v.max()
    iz, iy, ix = np.nonzero(keep)
    X = lo + np.stack([vol.x[ix], vol.y[iy], vol.z[iz]], 1)
    wgt = v[keep]
    c = np.average(X, axis=0, weights=wgt)
    w = c - pts.mean(0)
    w /= np.linalg.norm(w)
    ex = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ex - (ex @ w) * w
    u /= np.linalg.norm(u)
    return (c, u, np.cross(w, u), w), X, wgt


def hidden_surface_from_stir(capture, visible: VisiblePatches, settings: SurfaceSettings | None = None,
                             ill_step: int = 2, obs_step: int = 1, frame=None, irf=None,
                             search_margin: float = 0.8, margin: float = 0.25, depth_pad: float = 0.3,
                             n_lateral: int = 24, n_depth: int = 48) -> StirSurface:
    """Reconstruct the hidden surface of a full-STIR ``capture`` from its third bounce off the
    ``visible`` patches (see the module docstring). ``settings`` default: 8 x 8 nodes, one
    level, known gain. ``frame`` (c, u, v, w): the depth map's frame (else found, step 3).

    Returns ``StirSurface`` (surface fit, relay, initialising volume and maps, frame, and stats:
    wall times per stage, traces, peak resident memory of the process)."""
    t0 = time.perf_counter()
    rl = third_bounce_relay(capture, visible, ill_step, obs_step, irf)
    t1 = time.perf_counter()
    stats = {"traces": rl.n_traces, "ill_step": ill_step, "obs_step": obs_step,
             "subtract_s": t1 - t0}
    if frame is None:
        frame, X, _ = _find_frame(rl, search_margin, 32, 1500)
    else:
        frame = tuple(np.asarray(a, float) for a in frame)
        X = None
    t2 = time.perf_counter()
    stats["frame_s"] = t2 - t1
    c, u, v, w = frame
    if X is None:
        x0, x1, y0, y1 = -0.5, 0.5, -0.5, 0.5
    else:
        a, b = (X - c) @ u, (X - c) @ v
        ga, gb = margin * max(np.ptp(a), 0.05), margin * max(np.ptp(b), 0.05)
        x0, x1, y0, y1 = a.min() - ga, a.max() + ga, b.min() - gb, b.max() + gb
    # the depth map's origin sits depth_pad before the plane: BP depths are >= 0
    frame = (c - depth_pad * w, u, v, w)
    rl = _with_frame(rl, frame)
    vst = VolumeSettings(gate_m=0.0, n_lateral=n_lateral, xy_range=(x0, x1, y0, y1),
                         z_range=(0.0, 2 * depth_pad), n_depth=n_depth, bp_filter="laplacian")
    vol = backprojection(rl, vst)
    maps = vol.maps()
    t3 = time.perf_counter()
    stats["backprojection_s"] = t3 - t2
    st = settings or SurfaceSettings(n_nodes=8, levels=1, known_gain=True, max_iter=40)
    surf = fit_surface(rl, maps, st, gate=None)
    stats["surface_s"] = time.perf_counter() - t3
    stats["total_s"] = time.perf_counter() - t0
    stats["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return StirSurface(surf, rl, vol, maps, frame, stats)


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
