"""apps.replace: a new material re-renders as the forward model of the scene built with it;
energy-creating materials, unknown ids and unknown materials are refused."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.apps.belief import SceneBelief
from stircasadi.apps.render import RenderSettings
from stircasadi.apps.replace import make_brdf, replace_material
from stircasadi.apps.segment import segment
from stircasadi.apps.twin import estimate_from_scene
from stircasadi.brdf import Lambertian, Phong
from stircasadi.errors import BRDFError, EstimateInputError, SceneError
from stircasadi.problems import glossy_patch, hidden_corner, lambertian_walls
from stircasadi.scene import Patch, Scene
from stircasadi.transport import simulate

STD = {"position": 0.002, "normal": 0.01, "area": 1e-5, "albedo": 0.01}


def test_replacement_equals_the_forward_model_of_the_new_scene():
    scene, sensor = lambertian_walls.build_scene(), lambertian_walls.build_sensor()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    new = Phong(0.2, 0.6, 30.0)
    rep = replace_material(b, new, ids=[2, 5], sensor=sensor)
    swapped = Scene([Patch(p.centre, p.normal, p.area, new if k in (2, 5) else p.brdf, name=p.name)
                     for k, p in enumerate(scene.patches)])
    ref = simulate(swapped, rep.after.grid, sensor=sensor)
    assert np.max(np.abs(rep.after.stir - ref.stir)) <= 1e-12 * ref.stir.max()
    np.testing.assert_array_equal(rep.before.stir, simulate(scene, rep.before.grid, sensor=sensor).stir)
    assert rep.after.steady_std is not None and np.all(rep.after.steady_std >= 0)


def test_darker_lambertian_scales_the_direct_return_exactly():
    """Albedo 0.8 -> 0.4 on patch 0 of the corner: its own first bounce halves, paths that do
    not touch it are unchanged."""
    scene, sensor = hidden_corner.build_scene(), hidden_corner.build_sensor()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    rep = replace_material(b, Lambertian(0.4), ids=[0], sensor=sensor,
                           settings=RenderSettings(with_std=False, bounces=1))
    np.testing.assert_allclose(rep.after.stir[0, 0], 0.5 * rep.before.stir[0, 0], rtol=1e-12)
    np.testing.assert_allclose(rep.after.stir[1, 1], rep.before.stir[1, 1], rtol=0)


def test_segment_material_is_replaced_as_a_whole():
    scene = lambertian_walls.build_scene()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD))
    seg = segment(b)
    rep = replace_material(b, Lambertian(0.1), segmentation=seg, material=0,
                           settings=RenderSettings(with_std=False))
    assert sorted(rep.ids.tolist()) == sorted(seg.materials[0]["ids"])
    with pytest.raises(SceneError, match=r"Unknown material 99; the segmentation has materials 0\.\."):
        replace_material(b, Lambertian(0.1), segmentation=seg, material=99)


def test_bad_replacements_are_refused():
    scene = glossy_patch.build_scene()
    b = SceneBelief.from_estimate(estimate_from_scene(scene, STD | {"specular": 0.01, "exponent": 1.0}))
    with pytest.raises(BRDFError, match=r"creates energy: albedo \+ specular = 0.7 \+ 0.5 = 1.2 > 1"):
        make_brdf("phong", 0.7, 0.5, 10.0)
    with pytest.raises(BRDFError, match="not physical"):
        make_brdf("lambertian", 1.3)
    with pytest.raises(BRDFError, match="missing"):
        make_brdf("phong", 0.3)
    with pytest.raises(SceneError, match=r"Unknown patch id\(s\) \[12\]"):
        replace_material(b, Lambertian(0.5), ids=[1, 12])
    with pytest.raises(SceneError, match="not both, not neither"):
        replace_material(b, Lambertian(0.5))
    hc = SceneBelief.from_estimate(estimate_from_scene(hidden_corner.build_scene(), STD,
                                                       hidden_as_albedo_area=True))
    with pytest.raises(EstimateInputError, match=r"\[3\] are known only through albedo x area"):
        replace_material(hc, Lambertian(0.5), ids=[3])
