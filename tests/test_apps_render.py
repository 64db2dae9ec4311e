"""apps.render: rendering the estimate for a new camera / source, with the std propagated from
its covariance; the linearised std against a Monte Carlo, and its coverage on a twin."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.apps.belief import SceneBelief
from stircasadi.apps.relight import Illumination
from stircasadi.apps.render import RenderSettings, auto_grid, monte_carlo, render, steady_state
from stircasadi.apps.twin import estimate_from_scene
from stircasadi.errors import EstimateInputError, IlluminationError
from stircasadi.problems import hidden_corner
from stircasadi.transport import simulate

STD = {"position": 0.003, "normal": 0.02, "area": 2e-4, "albedo": 0.02}
NOVEL_CAMERA = (0.0, 0.0, 0.9)        # sees the hidden patches of the corner directly
NEW_SOURCE = (0.0, 0.05, 0.9)         # can aim at the hidden patches (never lit in the capture)
N_DRAWS = 50


def _truth():
    return hidden_corner.build_scene(), hidden_corner.build_sensor()


def test_render_at_the_truth_is_the_forward_model():
    scene, sensor = _truth()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    r = render(b, sensor=sensor, camera=NOVEL_CAMERA, settings=RenderSettings(with_std=False))
    moved = b.scene_at(b.values, camera=NOVEL_CAMERA)
    ref = simulate(moved, r.grid, sensor=sensor)
    np.testing.assert_array_equal(r.ill_ids, [0, 1]) and np.testing.assert_array_equal(r.obs_ids, [0, 1, 2, 3])
    np.testing.assert_array_equal(r.stir, ref.stir)
    np.testing.assert_allclose(r.steady, steady_state(moved), rtol=0)
    # seen from there no patch is hidden: second bounces are all the scene needs
    assert r.metadata["bounces"] == 2 and r.metadata["std_complete"]


def test_linearised_std_matches_a_monte_carlo_over_parameter_draws():
    scene, sensor = _truth()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD, correlation=0.3))
    ill = Illumination([1.0, 0.5], ids=[0, 1], delays=[0.0, 0.05])
    r = render(b, sensor=sensor, camera=NOVEL_CAMERA, illumination=ill)
    mc = monte_carlo(b, 400, np.random.default_rng(3), grid=r.grid, sensor=sensor, camera=NOVEL_CAMERA,
                     illumination=ill)
    ratio = mc["relit_steady"] / r.relit_steady_std
    assert np.all((ratio > 0.85) & (ratio < 1.15)), ratio      # 400 draws: sample std within ~7 %
    big = r.relit > 0.05 * r.relit.max()
    rt = mc["relit"][big] / r.relit_std[big]
    assert 0.9 < np.median(rt) < 1.1 and np.percentile(rt, 95) < 1.35


@pytest.mark.parametrize("config", [{"camera": NOVEL_CAMERA}, {"source": NEW_SOURCE}],
                         ids=["novel-view", "new-source"])
def test_twin_render_covers_the_truth_within_the_propagated_std(config):
    """Estimates drawn from N(truth, Sigma) (seeded): the render of each, +- its propagated std,
    covers the true scene's render at the stated rate (95 % at 1.96 sigma)."""
    scene, sensor = _truth()
    truth = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    ref = render(truth, sensor=sensor, settings=RenderSettings(with_std=False), **config)
    rng = np.random.default_rng(2024)
    z_steady, z_bins = [], []
    big = ref.stir > 0.05 * ref.stir.max()
    for _ in range(N_DRAWS):
        b = SceneBelief.from_estimate(estimate_from_scene(scene, STD, rng=rng, correlation=0.2))
        r = render(b, grid=ref.grid, sensor=sensor, **config)
        np.testing.assert_array_equal(r.obs_ids, ref.obs_ids)
        z_steady.append(((r.steady - ref.steady) / r.steady_std).ravel())
        z_bins.append(((r.stir - ref.stir)[big] / r.stir_std[big]))
    zs, zb = np.concatenate(z_steady), np.concatenate(z_bins)
    cover_s, cover_b = np.mean(np.abs(zs) < 1.96), np.mean(np.abs(zb) < 1.96)
    assert 0.88 <= cover_s <= 0.99, cover_s
    assert 0.88 <= cover_b <= 0.99, cover_b
    assert 0.8 < np.std(zs) < 1.25


def test_configurations_that_cannot_be_rendered_are_refused():
    scene, sensor = _truth()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    only_v1 = SceneBelief.from_estimate(estimate_from_scene(scene, STD), exclude=[1, 2, 3])
    with pytest.raises(EstimateInputError, match="nothing to render"):   # behind V1's back
        render(only_v1, sensor=sensor, camera=(0.0, 0.0, 3.0), settings=RenderSettings(with_std=False))
    with pytest.raises(IlluminationError, match=r"Unknown illuminated patch id\(s\) \[3\]"):
        render(b, sensor=sensor, illumination=Illumination([1.0], ids=[3]),
               settings=RenderSettings(with_std=False))
    with pytest.raises(EstimateInputError, match="bounces"):
        render(b, settings=RenderSettings(bounces=0))


def test_auto_grid_holds_every_path_of_the_order():
    scene, sensor = _truth()
    g = auto_grid(scene, 0.005, sensor, 3)
    simulate(scene, g, sensor=sensor, bounces=3)  # would raise TimeGridError if cut
    assert g.is_integer_aligned()
