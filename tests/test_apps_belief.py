"""apps.belief: estimate.json -> Scene, parameter vector and covariance; what cannot be rendered."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from stircasadi.apps.belief import PROXY_ALBEDO, SceneBelief
from stircasadi.apps.render import RenderSettings, render
from stircasadi.apps.twin import estimate_from_scene
from stircasadi.errors import EstimateInputError
from stircasadi.problems import glossy_patch, hidden_corner
from stircasadi.transport import simulate

STD = {"position": 0.002, "normal": 0.01, "area": 1e-4, "albedo": 0.01, "specular": 0.02, "exponent": 1.0}


def test_belief_reproduces_the_scene_and_its_covariance():
    scene = glossy_patch.build_scene()
    d = estimate_from_scene(scene, STD, correlation=0.3)
    b = SceneBelief.from_estimate(d)
    assert np.allclose(b.scene.positions, scene.positions) and np.allclose(b.scene.normals, scene.normals)
    assert [p.brdf for p in b.scene.patches] == [p.brdf for p in scene.patches]
    # the joint covariance is taken as given (names matched), correlations included
    names = d["covariance"]["parameters"]
    C = np.array(d["covariance"]["matrix"])
    idx = [b.names.index(n) for n in names]
    np.testing.assert_array_equal(b.covariance[np.ix_(idx, idx)], C)
    k1, k2 = b.names.index("albedo[1]"), b.names.index("albedo[2]")
    assert b.covariance[k1, k2] == pytest.approx(0.3 * 0.01 ** 2)
    # without the joint block: block-diagonal from the per-number std
    d2 = estimate_from_scene(scene, STD, joint=False)
    b2 = SceneBelief.from_estimate(d2)
    assert b2.covariance[k1, k2] == 0.0 and b2.covariance[k1, k1] == pytest.approx(1e-4)
    assert np.count_nonzero(b2.covariance - np.diag(np.diag(b2.covariance))) == 0


def test_scene_at_rebuilds_from_a_parameter_vector():
    scene = hidden_corner.build_scene()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    th = b.values.copy()
    th[b.slot("albedo", 2)] = 0.33
    th[b.slot("normal", 0)] = [0.0, 0.0, -2.0]        # renormalised
    sc = b.scene_at(th, camera=(0.0, 0.2, 0.0))
    assert sc.patches[2].brdf.albedo == 0.33 and np.allclose(sc.normals[0], [0, 0, -1])
    assert np.allclose(sc.camera, [0.0, 0.2, 0.0]) and np.allclose(sc.source, 0.0)


@pytest.mark.parametrize("field, value, words", [
    ("position", None, ["patch 2", "position is null", "exclude"]),
    ("position", [0.1, None, 0.5], ["patch 2", "position is null"]),
    ("normal", None, ["patch 2", "normal is null"]),
])
def test_null_geometry_is_refused_naming_patch_and_fix(field, value, words):
    d = estimate_from_scene(hidden_corner.build_scene(), STD)
    d["patches"][2][field] = value
    d["patches"][2]["notes"] = {field: "third bounces do not place it"}
    with pytest.raises(EstimateInputError) as e:
        SceneBelief.from_estimate(d)
    for w in words + ["third bounces do not place it"]:
        assert w in str(e.value)
    # the named fix works: excluding the patch renders the rest
    b = SceneBelief.from_estimate(d, exclude=[2])
    assert b.scene.n_patches == 3 and 2 not in b.ids


def test_visible_patch_without_area_needs_a_declared_area():
    d = estimate_from_scene(hidden_corner.build_scene(), STD)
    d["patches"][0]["area"] = None
    with pytest.raises(EstimateInputError, match=r"patch 0 \(V1\): area is null.*areas=\{0: A\}"):
        SceneBelief.from_estimate(d)
    b = SceneBelief.from_estimate(d, areas={0: 0.01})
    assert b.scene.areas[0] == 0.01 and b.std[b.slot("area", 0)][0] == 0.0
    assert any("declared" in n for n in b.notes)
    with pytest.raises(EstimateInputError, match="not in the estimate"):
        SceneBelief.from_estimate(d, areas={9: 0.01})


def test_unreliable_estimate_is_refused_unless_allowed():
    d = estimate_from_scene(hidden_corner.build_scene(), STD)
    d.update(success=False, verdict="UNRELIABLE", reasons=["chi2: 14.2 > 3.0"])
    with pytest.raises(EstimateInputError, match=r"UNRELIABLE \(chi2: 14.2 > 3.0\).*allow_unreliable"):
        SceneBelief.from_estimate(d)
    assert SceneBelief.from_estimate(d, allow_unreliable=True).verdict == "UNRELIABLE"


@pytest.mark.parametrize("mutate, words", [
    (lambda c: c["matrix"].__setitem__(0, [1.0] * len(c["matrix"])), "not symmetric"),
    (lambda c: c.__setitem__("parameters", c["parameters"][:-1]), "must be"),
    (lambda c: c["parameters"].__setitem__(0, "albedo 3"), "kind[ID]"),
])
def test_malformed_covariance_is_refused(mutate, words):
    d = estimate_from_scene(hidden_corner.build_scene(), STD)
    mutate(d["covariance"])
    with pytest.raises(EstimateInputError, match=words.replace("[", r"\[").replace("]", r"\]")):
        SceneBelief.from_estimate(d)


def test_hidden_patch_known_only_as_albedo_area_renders_exactly_while_pass_through():
    """Paths through a hidden Lambertian patch depend on it only through albedo x area: the proxy
    (albedo PROXY_ALBEDO, area albedo_area / PROXY_ALBEDO) renders the true STIR exactly."""
    scene = hidden_corner.build_scene()
    grid, sensor = hidden_corner.build_grid(), hidden_corner.build_sensor()
    d = estimate_from_scene(scene, STD, hidden_as_albedo_area=True)
    assert d["patches"][2]["area"] is None and d["patches"][2]["albedo_area"] == pytest.approx(0.7 * 0.04)
    b = SceneBelief.from_estimate(d)
    assert b.proxy_ids == (2, 3) and b.scene.patches[2].brdf.albedo == PROXY_ALBEDO
    truth = simulate(scene, grid, sensor=sensor).stir
    got = render(b, grid=grid, sensor=sensor, settings=RenderSettings(with_std=False)).stir
    assert np.max(np.abs(got - truth)) <= 1e-12 * np.max(truth)
    # a camera that sees the hidden patch needs its albedo alone: refused, naming the fix
    with pytest.raises(EstimateInputError, match=r"Patch 2 \(H1\).*albedo x area.*areas=\{2: A\}"):
        render(b, sensor=sensor, camera=(0.0, 0.0, 0.9), settings=RenderSettings(with_std=False))


def test_estimate_with_wrong_format_or_no_patches_is_refused():
    with pytest.raises(EstimateInputError, match="format"):
        SceneBelief.from_estimate({"format": "other", "version": 2, "patches": []})
    d = estimate_from_scene(hidden_corner.build_scene(), STD)
    d2 = copy.deepcopy(d)
    d2["patches"] = []
    with pytest.raises(EstimateInputError, match="no 'patches'"):
        SceneBelief.from_estimate(d2)
    d3 = copy.deepcopy(d)
    d3["patches"][1]["specular"] = 0.2
    with pytest.raises(EstimateInputError, match="both specular and exponent"):
        SceneBelief.from_estimate(d3)
