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
