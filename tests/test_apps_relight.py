"""apps.relight: superposition of the measured STIR equals the forward model driven by the new
illumination (to 1e-12 relative); bad illuminations are refused clearly."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.apps.lti import drive_state_space, inputs_from_illumination
from stircasadi.apps.relight import Illumination, nayar_patterns, relight_capture, superpose
from stircasadi.apps.render import steady_state
from stircasadi.errors import IlluminationError
from stircasadi.problems import lambertian_walls, three_patch
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import radiosity, simulate


@pytest.mark.parametrize("problem", [three_patch, lambertian_walls])
def test_superposition_equals_the_state_space_driven_by_the_pattern(problem):
    """Weights, whole-bin delays and pulse shapes on every lit patch at once: the STIR superposed
    equals x[t+1] = A x + B u[t] run with that input (every bounce, integer delays)."""
    scene, sensor, g0 = problem.build_scene(), problem.build_sensor(), problem.build_grid()
    grid = TimeGrid(0.0, g0.bin_width, int(g0.end / g0.bin_width) + 40)
    tr = simulate(scene, grid, sensor=sensor, method="statespace", delay_mode="integer")
    n = len(tr.ill_ids)
    rng = np.random.default_rng(7)
    ill = Illumination(rng.uniform(0.0, 1.0, n), ids=tr.ill_ids,
                       delays=rng.integers(0, 40, n) * grid.bin_width, pulses=rng.uniform(0, 1, (n, 9)))
    relit = superpose(tr.stir, grid, tr.ill_ids, tr.obs_ids, ill)
    u = inputs_from_illumination(tr.ill_ids, ill, grid.bin_width, grid.n_bins + 10)
    ref, obs = drive_state_space(scene, grid, u, sensor)
    np.testing.assert_array_equal(obs, tr.obs_ids)
    assert np.max(np.abs(relit.transient - ref)) <= 1e-12 * np.max(np.abs(ref))
    assert relit.metadata["integer_delays"] and relit.metadata["fractional_error_bound"] == 0.0


def test_sub_bin_delays_match_the_exact_delay_forward_model():
    """Fractional delays (phase ramp) against simulate() on grids shifted by each delay."""
    scene, sensor = three_patch.build_scene(), three_patch.build_sensor()
    grid = TimeGrid(1.5, 0.005, 400)
    tr = simulate(scene, grid, sensor=sensor)
    rng = np.random.default_rng(1)
    w, d, p = rng.uniform(0.2, 1, 3), rng.uniform(0, 0.3, 3), rng.uniform(0, 1, (3, 4))
    relit = superpose(tr.stir, grid, tr.ill_ids, tr.obs_ids, Illumination(w, tr.ill_ids, d, p), irf=sensor.irf)
    ref = np.zeros_like(relit.transient)
    for i in range(3):
        for m in range(4):
            shifted = TimeGrid(grid.start - d[i] - m * grid.bin_width, grid.bin_width, grid.n_bins)
            ref += w[i] * p[i, m] * simulate(scene, shifted, sensor=sensor, allow_truncation=True).stir[i]
    assert np.max(np.abs(relit.transient - ref)) <= 1e-12 * np.max(ref)
    assert relit.metadata["fractional_error_bound"] < 1e-30   # 210 ps response on 5 mm bins


def test_steady_state_relighting_equals_radiosity_of_the_pattern():
    """CW light over the patches: superposed steady state = classic radiosity (every bounce, an
    independent solver), when the STIR carries every bounce."""
    scene = three_patch.build_scene()
    grid = TimeGrid(0.0, 0.01, 3000)
    tr = simulate(scene, grid, sensor=Sensor(), bounces="all", method="frequency", delay_mode="integer")
    w = np.array([0.2, 1.0, 0.5])
    relit = superpose(tr.stir, grid, tr.ill_ids, tr.obs_ids, Illumination(w))
    ref = w @ radiosity(scene)
    np.testing.assert_allclose(relit.steady, ref, rtol=1e-9)
    np.testing.assert_allclose(w @ steady_state(scene), ref, rtol=1e-12)


def test_relight_capture_uses_ids_and_refuses_bad_illuminations():
    scene, sensor, grid = three_patch.build_scene(), three_patch.build_sensor(), three_patch.build_grid()
    cap = sensor.capture(simulate(scene, grid, sensor=sensor), seed=0, noise=False)
    a = relight_capture(cap, Illumination([2.0], ids=[1]))
    np.testing.assert_allclose(a.transient, 2.0 * cap.stir[1], rtol=0, atol=0)
    with pytest.raises(IlluminationError, match=r"4 weights but the STIR has 3 illuminated patches \(ids \[0, 1, 2\]\)"):
        relight_capture(cap, Illumination([1, 1, 1, 1]))
    with pytest.raises(IlluminationError, match=r"Unknown illuminated patch id\(s\) \[7\].*--estimate"):
        relight_capture(cap, Illumination([1.0], ids=[7]))
    with pytest.raises(IlluminationError, match="finite"):
        relight_capture(cap, Illumination([1.0, np.nan, 1.0]))
    with pytest.raises(IlluminationError, match=">= 0 metres"):
        relight_capture(cap, Illumination([1.0, 1.0, 1.0], delays=[0.0, -0.1, 0.0]))
    with pytest.raises(IlluminationError, match="names a patch twice"):
        relight_capture(cap, Illumination([1.0, 1.0], ids=[0, 0]))


def test_nayar_patterns_are_complementary_checkerboards():
    a, b = nayar_patterns(np.arange(6), layout=[(r, c) for r in range(2) for c in range(3)])
    np.testing.assert_array_equal(a.weights + b.weights, np.ones(6))
    np.testing.assert_array_equal(a.weights, [1, 0, 1, 0, 1, 0])
    with pytest.raises(IlluminationError, match="layout"):
        nayar_patterns(np.arange(6), layout=[(0, 0)])
