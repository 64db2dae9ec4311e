"""Fig. 13 by the surface route (``stircasadi.nlos.stir_surface``): the relay model's third
bounce against ``transport.simulate`` for one hidden patch (the known answer the gain and legs
rest on), and the hidden panel of ``three_planes_occluded`` reconstructed from its full STIR."""
import numpy as np
import pytest

from stircasadi.irf import GaussianIRF
from stircasadi.nlos.stir_surface import VisiblePatches, third_bounce_relay
from stircasadi.nlos.surface.grid import DepthGrid
from stircasadi.nlos.surface.model import SurfaceModel, SurfaceState
from stircasadi.nlos.surface.response import Response
from stircasadi.problems import three_planes_occluded as P
from stircasadi.scene import Scene
from stircasadi.sensor import Sensor
from stircasadi.transport import simulate


def test_relay_third_bounce_matches_transport_for_one_hidden_patch():
    """Three visible patches of Fig. 13 (back wall, right panel), one hidden patch of the left
    panel behind the screen, legs included: the STIR minus the visible patches' own simulated
    STIR, read through ``third_bounce_relay`` (gain rho_L rho_D / pi^2, legs |s - L| + |D - o|),
    equals the surface model's prediction for that patch, trace by trace and bin by bin."""
    base = P.build_scene()
    keep = [24, 20, 122, 73]                      # 3 visible, 1 behind the screen
    scene = Scene([base.patches[k] for k in keep], occluders=base.occluders)
    assert list(np.flatnonzero(scene.hidden)) == [3]
    g = P.build_grid()
    irf = GaussianIRF.from_ps(210.0)
    tr = simulate(scene, g, Sensor(irf=irf), bounces=3, legs_included=True, allow_truncation=True)
    cap = Sensor(irf=irf).capture(tr, noise=False)
    vis = VisiblePatches(np.arange(3), scene.positions[:3], scene.normals[:3], scene.albedos[:3],
                         scene.areas[:3], scene.occluders)
    rl = third_bounce_relay(cap, vis)
    assert rl.n_traces == 9
    X, nX, a, rho = scene.positions[3], scene.normals[3], scene.areas[3], scene.albedos[3]
    # a 3 x 3 grid of 1 mm cells centred on the patch, parallel to it; only the centre node
    # carries albedo, scaled so that its cell (1 mm^2) reflects what the patch's area does
    h = 1e-3
    w = -nX
    t = np.cross(w, [0.0, 1.0, 0.0])
    u = t / np.linalg.norm(t)
    frame = (X - 0.3 * w, u, np.cross(w, u), w)
    grid = DepthGrid(np.array([-h, 0, h]), np.array([-h, 0, h]), frame)
    rho_n = np.zeros(9)
    rho_n[4] = rho * a / h ** 2
    model = SurfaceModel(grid, rl, Response("gaussian", irf.sigma, 0.0), subsamples=1)
    m = model.predict(SurfaceState(np.full(9, 0.3), rho_n, irf.sigma, 0.0, (), 0.0))
    y = rl.traces
    assert y.max() > 0 and np.count_nonzero(y.sum(axis=1) > 1e-3 * y.sum(axis=1).max()) >= 4
    # time integrals: the amplitude (gain, falloffs, cosines) to 1e-6 relative
    np.testing.assert_allclose(m.sum(axis=1), y.sum(axis=1), rtol=1e-6, atol=1e-6 * y.sum(axis=1).max())
    # bin by bin: delays with legs and the response (the 1 mm cell's own spread is ~1e-4 of it)
    assert np.max(np.abs(m - y)) <= 2e-3 * np.max(y)


def test_compare_with_patches_reads_the_surface_at_the_patch_columns():
    """A plane surface result against patches on it (zero error), then shifted along w and
    tilted: the comparison returns that shift, the tilt angle and |err| / std."""
    from stircasadi.nlos.stir_surface import compare_with_patches
    from stircasadi.nlos.surface.result import SurfaceResult

    rng = np.random.default_rng(3)
    c, u, v, w = np.array([0.1, 0.2, 1.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0])
    grid = DepthGrid(np.linspace(-0.3, 0.3, 7), np.linspace(-0.3, 0.3, 7), (c, u, v, w))
    depth = 0.4 + 0.2 * grid.base_points()[:, 0].reshape(7, 7) - 0.2 * c[0]
    _, nrm, _ = grid.geometry(depth.ravel())
    mask = np.ones((7, 7), bool)
    mask[0] = False
    res = SurfaceResult(grid, depth, np.ones((7, 7)), nrm.reshape(7, 7, 3), np.full((7, 7), 0.002),
                        np.ones((7, 7)), np.zeros((7, 7, 3)), mask, 0.01, None, 0.0, 1.0, 0.0, "none",
                        1.0, 100, False, True)
    ab = rng.uniform(-0.25, 0.25, (20, 2))
    P_ = c + ab[:, :1] * u + ab[:, 1:] * v + (0.4 + 0.2 * ab[:, :1]) * w
    n_true = np.tile(nrm[0], (20, 1))
    m = compare_with_patches(res, P_, n_true)
    assert np.max(np.abs(m["depth_err"])) < 1e-12 and np.max(m["normal_deg"]) < 1e-6
    assert np.array_equal(m["inside"], ab[:, 1] > -0.25)          # the first row is masked out
    tilt = np.radians(5.0)
    n2 = np.tile([nrm[0, 0], np.sin(tilt), nrm[0, 2]], (20, 1))
    n2 /= np.linalg.norm(n2, axis=1, keepdims=True)
    m = compare_with_patches(res, P_ + 0.005 * w, n2)
    np.testing.assert_allclose(m["depth_err"], -0.005, atol=1e-12)
    np.testing.assert_allclose(m["z_score"], 2.5, rtol=1e-9)
    ang = np.degrees(np.arccos(np.clip(n2 @ nrm[0], -1, 1)))
    np.testing.assert_allclose(m["normal_deg"], ang, atol=1e-9)
    assert ang[0] > 3.0


def test_matched_score_peaks_on_the_hidden_panel():
    """The panel's third bounce at 1e-8 relative noise (every 8th illumination): the
    point-scatterer score (step 3 of the frame search) is at least as high on the true hidden
    patches as anywhere on the search box's grid, and far above the visible patches'."""
    import stircasadi.nlos.stir_surface as S
    from stircasadi.problems._common import paper_sensor

    sc, sen = P.build_scene(), paper_sensor(1e-8)
    cap = sen.capture(simulate(sc, P.build_grid(), sensor=sen), seed=5)
    rl = third_bounce_relay(cap, VisiblePatches.from_scene(sc), ill_step=8)
    _, X, wgt = S._find_frame(rl, 0.8, 32, 1500)
    on_panel = S.matched_score(rl, sc.positions[sc.hidden])
    off = S.matched_score(rl, sc.positions[~sc.hidden] + 0.05 * sc.normals[~sc.hidden])
    assert on_panel.max() >= 0.9 * wgt.max()
    assert np.median(on_panel) > 10 * max(np.median(np.abs(off)), 1.0)
