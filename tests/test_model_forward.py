"""The symbolic model equals the numeric forward model (1e-9 relative) and guards its declaration."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.problems import glossy_patch, hidden_corner, hidden_mirrors, lambertian_walls, three_patch
from stircasadi.brdf import Lambertian, Mirror
from stircasadi.errors import ModelError
from stircasadi.irf import from_samples
from stircasadi.model import TransientModel
from stircasadi.scene import Patch, Scene
from stircasadi.irf import GaussianIRF, IdealIRF
from stircasadi.transport import simulate

from _reflectance_helpers import hidden_model


def _truth_values(sc):
    t = sc.truth_dict()
    return {"albedo": t["albedo"], "specular": t.get("specular", np.zeros(sc.n_patches)),
            "exponent": t.get("exponent", np.zeros(sc.n_patches)), "position": sc.positions}


@pytest.mark.parametrize("mod,kw", [(three_patch, {}), (hidden_corner, {}), (glossy_patch, {}),
                                    (lambertian_walls, {"n_patches": 10})])
def test_symbolic_equals_numeric_forward(mod, kw):
    sc, gr, se = mod.build_scene(**kw), mod.build_grid(), mod.build_sensor()
    tr = simulate(sc, gr, se)
    m = TransientModel.from_scene(sc, gr, se.irf)
    m.set_unknown("albedo", "all", initial=0.5)
    if sc.is_glossy:
        m.set_unknown("specular", "glossy", initial=0.1).set_unknown("exponent", "glossy", initial=3.0)
    h = np.flatnonzero(sc.hidden)
    if len(h):  # symbolic (erf) kernels for the paths through hidden patches
        m.set_unknown("position", h, lower=-0.02, upper=0.02)
    m.setup()
    x = m.x_of(_truth_values(sc))
    y = m.simulate(x)
    rel = np.abs(y - tr.stir).max() / np.abs(tr.stir).max()
    assert rel < 1e-9, rel
    # and a wrong parameter value does not match (the comparison can fail)
    assert np.abs(m.simulate() - tr.stir).max() / np.abs(tr.stir).max() > 1e-3
    # the NumPy path sums (the probe a model set up without its CasADi graph uses) equal the
    # symbolic output at the truth and away from it
    for xx in (x, m.x0):
        assert np.abs(m.simulate(xx, numeric=True) - m.simulate(xx)).max() <= 1e-12 * np.abs(tr.stir).max()


def test_legs_excluded_and_plane_parameterisation_match():
    sc, gr, se = hidden_corner.build_scene(), hidden_corner.build_grid(), hidden_corner.build_sensor()
    tr = simulate(sc, gr, se)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.01, -0.01], [0.0, 0.005]])
    m.setup()
    th = m.theta(m.x_of({"albedo": sc.albedos, "position": sc.positions}))
    assert np.allclose(th["position"][h], sc.positions[h], atol=1e-12)
    y = m.simulate(m.x_of({"albedo": sc.albedos, "position": sc.positions}))
    assert np.abs(y - tr.stir).max() / tr.stir.max() < 1e-9
    from stircasadi.timegrid import TimeGrid
    sc3, gr3, se3 = three_patch.build_scene(), TimeGrid(-0.3, 0.005, 300), three_patch.build_sensor()
    tr3 = simulate(sc3, gr3, se3, legs_included=False)
    m3 = TransientModel.from_scene(sc3, gr3, se3.irf, legs_included=False).set_unknown("albedo").setup()
    y3 = m3.simulate(m3.x_of({"albedo": sc3.albedos}))
    assert np.abs(y3 - tr3.stir).max() / tr3.stir.max() < 1e-9


def test_mirrors_and_extended_patches_equal_the_numeric_model():
    """The symbolic model calls the numeric transport's leg formulas: image-source legs through
    mirror patches, and a hidden disc equal to its quadrature points simulated as patches."""
    from stircasadi.brdf import Mirror
    from stircasadi.model.vertices import disc_rule
    from stircasadi.problems._common import plane_patches, unit
    wall = plane_patches((0.0, 0.0, 1.5), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 4, 4, 0.15, 0.0064,
                         brdf=Lambertian(0.8), prefix="W")
    mirrors = [Patch((0.15, 0.1, 0.9), tuple(unit((0.0, 0.0, 1.0))), 0.02, Mirror(0.95), name="M1"),
               Patch((-0.2, -0.15, 1.0), tuple(unit((0.25, 0.1, 1.0))), 0.02, Mirror(0.95), name="M2")]
    sc = Scene(wall + mirrors)
    gr, se = hidden_mirrors.build_grid(), hidden_corner.build_sensor()
    tr = simulate(sc, gr, se, bounces=3)
    assert tr.metadata["mirror_legs"] > 0
    m = TransientModel.from_scene(sc, gr, se.irf, bounces=3).set_unknown("albedo", np.arange(16)).setup()
    y = m.simulate(m.x_of({"albedo": sc.albedos}))
    assert np.abs(y - tr.stir).max() / tr.stir.max() < 1e-12
    probe = TransientModel.from_scene(sc, gr, se.irf, bounces=3).set_unknown("albedo", np.arange(16))
    probe.setup(symbolic=False)      # paths only: NumPy sums, no graph
    assert not hasattr(probe, "f_y")
    assert np.abs(probe.simulate(probe.x_of({"albedo": sc.albedos})) - tr.stir).max() / tr.stir.max() < 1e-12
    # extended hidden patch vs its quadrature points as patches of the numeric model
    sc0, gr = hidden_corner.build_scene(), hidden_corner.build_grid()
    k = 3
    P = sc0.patches[k]
    m = TransientModel.from_scene(sc0, gr, se.irf).set_unknown("albedo", [0, 1]).set_extended([k]).setup()
    n = np.array(P.normal)
    t1 = np.cross(m.frame_ref[k], n)
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    R = np.sqrt(P.area / np.pi)
    u, v, w = disc_rule(2, 6)
    subs = [Patch(tuple(np.array(P.centre) + R * (a * t1 + b * t2)), P.normal, P.area * ww, P.brdf)
            for a, b, ww in zip(u, v, w)]
    sc1 = Scene([p for i, p in enumerate(sc0.patches) if i != k] + subs)
    tr1 = simulate(sc1, gr, se, bounces=3)
    y = m.simulate(m.x_of({"albedo": sc0.albedos}))
    assert np.abs(y - tr1.stir).max() / tr1.stir.max() < 1e-12
    assert np.abs(m.simulate(m.x_of({"albedo": sc0.albedos}), numeric=True) - tr1.stir).max() / tr1.stir.max() < 1e-12
    # and the disc differs from the point patch (the extent shows in the transient)
    tr0 = simulate(sc0, gr, se, bounces=3, per_bounce=True)
    assert np.abs(y - tr0.stir).max() > 0.01 * tr0.per_bounce[2].max()


def test_ideal_irf_fixed_geometry_matches():
    sc, gr = three_patch.build_scene(), three_patch.build_grid()
    from stircasadi.sensor import Sensor
    tr = simulate(sc, gr, Sensor())
    m = TransientModel.from_scene(sc, gr, IdealIRF()).set_unknown("albedo").setup()
    y = m.simulate(m.x_of({"albedo": sc.albedos}))
    assert np.abs(y - tr.stir).max() / tr.stir.max() < 1e-9


def test_irf_from_samples_recovers_gaussian():
    g = GaussianIRF(0.04)
    from stircasadi.sensor import Sensor
    from stircasadi.timegrid import TimeGrid
    s = Sensor(irf=g).irf_samples(TimeGrid(0.0, 0.005, 10))
    fit = from_samples(s, 0.005)
    assert isinstance(fit, GaussianIRF)
    assert abs(fit.fwhm - 0.04) / 0.04 < 0.01


def test_declaration_errors_name_the_fix():
    sc, gr = three_patch.build_scene(), three_patch.build_grid()
    irf = GaussianIRF(0.03)
    with pytest.raises(ModelError, match="No unknowns declared"):
        TransientModel.from_scene(sc, gr, irf).setup()
    with pytest.raises(ModelError, match="outside its bounds"):
        TransientModel.from_scene(sc, gr, irf).set_unknown("albedo", initial=1.5).setup()
    with pytest.raises(ModelError, match="Unknown parameter"):
        TransientModel.from_scene(sc, gr, irf).set_unknown("roughness")
    with pytest.raises(ModelError, match="Phong parameter"):
        TransientModel.from_scene(sc, gr, irf).set_unknown("specular", [0])
    m = TransientModel.from_scene(sc, gr, irf).set_unknown("albedo").setup()
    with pytest.raises(ModelError, match="locked"):
        m.set_unknown("albedo")
    with pytest.raises(ModelError, match="differentiable"):
        (TransientModel.from_scene(sc, gr, IdealIRF())
         .set_unknown("position", [0], lower=-0.01, upper=0.01).setup())
    with pytest.raises(ModelError, match="must contain 0"):
        (TransientModel.from_scene(sc, gr, irf)
         .set_unknown("position", [0], lower=sc.positions[0] - 0.01, upper=sc.positions[0] + 0.01).setup())
    with pytest.raises(ModelError, match="finite bounds"):
        TransientModel.from_scene(sc, gr, irf).set_unknown("position", [0]).setup()
    mir = Scene([Patch((0, 0, 1), (0, 0, -1), 0.01, Lambertian(0.5)),
                 Patch((0.3, 0, 1.2), (0, 0, -1), 0.01, Mirror(0.9))])
    with pytest.raises(ModelError, match="mirror"):
        TransientModel.from_scene(mir, gr, irf).set_unknown("albedo", [1])
