"""BRDFs (energy, symbolic = numeric) and scene visibility by ray casting."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stircasadi.brdf import Lambertian, Mirror, Phong
from stircasadi.errors import BRDFError
from stircasadi.scene import Patch, Scene


def hemisphere_albedo(brdf, theta_in: float, n: int = 400) -> float:
    """Directional-hemispherical reflectance: int f cos(theta_out) d omega, midpoint rule."""
    th = (np.arange(n) + 0.5) * (math.pi / 2) / n
    ph = (np.arange(2 * n) + 0.5) * (2 * math.pi) / (2 * n)
    T, P = np.meshgrid(th, ph, indexing="ij")
    w_out = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1)
    w_in = np.array([math.sin(theta_in), 0.0, math.cos(theta_in)])
    cos_in = w_in[2]
    cos_out = w_out[..., 2]
    cos_io = w_out @ w_in
    f = brdf.value(np.full_like(cos_out, cos_in), cos_out, cos_io)
    dA = (math.pi / 2 / n) * (2 * math.pi / (2 * n))
    return float(np.sum(f * cos_out * np.sin(T)) * dA)


@pytest.mark.parametrize("brdf", [Lambertian(0.8), Phong(0.3, 0.7, 5.0), Phong(0.0, 1.0, 40.0),
                                  Phong(0.5, 0.5, 1.0)], ids=str)
@pytest.mark.parametrize("theta_in", [0.0, 0.6, 1.2])
def test_reflected_energy_never_exceeds_kd_plus_ks(brdf, theta_in):
    a = hemisphere_albedo(brdf, theta_in)
    assert a <= brdf.albedo + getattr(brdf, "specular", 0.0) + 2e-3
    if isinstance(brdf, Lambertian):
        assert a == pytest.approx(0.8, rel=1e-4)
    if theta_in == 0.0 and isinstance(brdf, Phong):
        # at normal incidence the modified Phong lobe integrates exactly to ks (closed form)
        assert a == pytest.approx(brdf.albedo + brdf.specular, rel=2e-3)


def test_same_formula_evaluates_on_casadi_symbols():
    import casadi as ca
    x = ca.SX.sym("x", 3)
    ci, co, cio = 0.7, 0.8, 0.3
    expr = Phong.formula(ci, co, cio, x[0], x[1], x[2])
    fn = ca.Function("f", [x], [expr, ca.jacobian(expr, x)])
    val, jac = fn([0.2, 0.5, 9.0])
    assert float(val) == pytest.approx(Phong(0.2, 0.5, 9.0).value(ci, co, cio), rel=1e-14)
    # derivative wrt the exponent against a central difference
    h = 1e-6
    fd = (Phong(0.2, 0.5, 9.0 + h).value(ci, co, cio) - Phong(0.2, 0.5, 9.0 - h).value(ci, co, cio)) / (2 * h)
    assert float(jac[2]) == pytest.approx(fd, rel=1e-6)


def test_brdf_bounds_are_enforced():
    with pytest.raises(BRDFError, match=r"\[0, 1\]"):
        Lambertian(1.2)
    with pytest.raises(BRDFError, match="energy conservation"):
        Phong(0.6, 0.5, 10)
    with pytest.raises(BRDFError, match="exponent"):
        Phong(0.2, 0.2, -1)
    with pytest.raises(BRDFError, match=r"\[0, 1\]"):
        Mirror(1.5)


def test_blocker_between_facing_patches_cuts_the_leg():
    import trimesh
    a = Patch((-0.5, 0, 1.0), (0.70710678118, 0, -0.70710678118), 0.01)
    b = Patch((0.5, 0, 1.0), (-0.70710678118, 0, -0.70710678118), 0.01)
    open_scene = Scene([a, b])
    assert open_scene.patch_visibility[0, 1] and open_scene.patch_visibility[1, 0]
    wall = trimesh.creation.box(extents=(0.02, 0.5, 0.5))
    wall.apply_translation((0.0, 0.0, 1.0))
    blocked = Scene([a, b], occluders=wall)
    assert not blocked.patch_visibility[0, 1] and not blocked.patch_visibility[1, 0]
    assert blocked.visible.all()            # the camera still sees both
    # a blocker in front of the camera hides a patch
    screen = trimesh.creation.box(extents=(0.3, 0.3, 0.01))
    screen.apply_translation((-0.25, 0.0, 0.5))
    hid = Scene([a, b], occluders=screen)
    assert hid.visible.tolist() == [False, True] and hid.hidden.tolist() == [True, False]


def test_mesh_self_occlusion():
    """An L of two walls: patches on each wall see the other wall, not through it."""
    import trimesh
    floor = trimesh.creation.box(extents=(1.0, 0.02, 0.9))
    floor.apply_translation((0, -0.5, 1.5))
    back = trimesh.creation.box(extents=(1.0, 1.0, 0.02))
    back.apply_translation((0, 0, 2.0))
    mesh = trimesh.util.concatenate([floor, back])
    sc = Scene.from_mesh(mesh, patch_size=0.5)
    assert sc.needs_occlusion
    # patches on the rear face of the back wall (z > 2, facing +z) see nothing on the near side
    far = (sc.positions[:, 2] > 2.005) & (sc.normals[:, 2] > 0.9)
    near = sc.positions[:, 2] < 1.995
    assert far.any() and near.any()
    assert not sc.patch_visibility[np.ix_(far, near)].any()
    assert not sc.visible[far].any()
    # while the floor's top face and the back wall's front face do see each other
    top = (sc.normals[:, 1] > 0.9) & (sc.positions[:, 1] < -0.48)
    front = (sc.normals[:, 2] < -0.9) & (np.abs(sc.positions[:, 2] - 1.99) < 1e-6)
    assert sc.patch_visibility[np.ix_(top, front)].any()
