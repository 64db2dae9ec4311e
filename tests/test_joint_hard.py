"""Hard cases stay stable: albedo at the energy limit, grazing angles, 1e-6 dynamic range, a poor
start, a hidden patch too faint to see (reported unidentifiable), failed solves, bad settings."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.problems import hidden_corner, lambertian_walls, three_patch
from stircasadi.problems._common import unit
from stircasadi.brdf import Lambertian
from stircasadi.errors import ModelError, SolverError
from stircasadi.joint import EstimateSettings, JointNLP, solve_lm
from stircasadi.joint.fit import fit_model
from stircasadi.joint.result import patch_records
from stircasadi.model import TransientModel
from stircasadi.scene import Patch, Scene
from stircasadi.irf import GaussianIRF
from stircasadi.sensor import GaussianNoise, Sensor

from _reflectance_helpers import capture_of, hidden_model, quiet


def _with_albedos(sc, alb):
    return Scene([Patch(p.centre, p.normal, p.area, Lambertian(a), p.hidden, p.name)
                  for p, a in zip(sc.patches, alb)], name=sc.name)


def test_albedos_at_the_energy_limit():
    base = lambertian_walls.build_scene(10)
    alb = np.array([0.999, 0.995, 1.0, 0.99, 0.98, 1.0, 0.999, 0.97, 0.995, 0.99])
    sc = _with_albedos(base, alb)
    sc, gr, se, tr, cap = capture_of(lambertian_walls, seed=3, scene=sc)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success
    assert np.all(e.values["albedo"] <= 1.0 + 1e-9)
    assert np.all(np.abs(e.values["albedo"] - alb) < 4 * e.std["albedo"] + 1e-6)
    c = np.asarray(JointNLP(m, cap.stir, quiet(), noise=cap.noise).f_g(e.x)).ravel()
    assert np.all(c <= 1.0)  # stability / energy constraint holds


def test_grazing_angle_patch():
    sc0 = three_patch.build_scene()
    z = np.array([0.35, 0.0, 1.0])
    u = -z / np.linalg.norm(z)
    perp = unit(np.cross(u, (0.0, 1.0, 0.0)))
    n = np.cos(np.radians(85.0)) * u + np.sin(np.radians(85.0)) * perp
    if np.dot(n, sc0.positions[1] - z) < 0:
        n = np.cos(np.radians(85.0)) * u - np.sin(np.radians(85.0)) * perp
    patches = [Patch(tuple(z), tuple(unit(n)), 0.01, Lambertian(0.7), name="grazing")] + list(sc0.patches[1:])
    sc = Scene(patches)
    assert abs(np.dot(unit(n), u)) < 0.1
    sc, gr, se, tr, cap = capture_of(three_patch, seed=5, scene=sc)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success and np.all(np.isfinite(e.std["albedo"]))
    assert np.all(np.abs(e.values["albedo"] - sc.albedos) < 4 * e.std["albedo"])


def _corner(hidden_areas, noise_rel):
    sc0 = hidden_corner.build_scene()
    patches = [Patch(p.centre, p.normal, hidden_areas[k - 2] if p.name.startswith("H") else p.area,
                     p.brdf, p.hidden, p.name) for k, p in enumerate(sc0.patches)]
    sensor = Sensor(irf=hidden_corner.build_sensor().irf,
                    noise=GaussianNoise(relative=noise_rel) if noise_rel else None)
    return Scene(patches, name="corner"), sensor


def test_dynamic_range_of_1e_minus_6_between_bounces():
    sc, sensor = _corner((2e-4, 2e-4), 1e-9)
    from stircasadi.transport import simulate
    tr = simulate(sc, hidden_corner.build_grid(), sensor, per_bounce=True)
    ratio = tr.per_bounce[2].max() / tr.per_bounce[0].max()
    assert 1e-7 < ratio < 3e-6, ratio
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=6, scene=sc, sensor=sensor)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.005, -0.004], [-0.004, 0.005]])
    m.setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success
    za = (e.values["albedo"] - sc.albedos) / e.std["albedo"]
    assert np.all(np.abs(za) < 4), za
    assert np.all(e.std["albedo"][h] < 0.05)
    assert np.abs(e.values["position"][h] - sc.positions[h]).max() < 0.2 * gr.bin_width


def test_poor_initial_guess_converges():
    # the noise this test was designed for (the problem's default is 1e-6)
    sensor = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(relative=1e-7))
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=8, sensor=sensor)
    eps = 0.03
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.6 * eps, -0.6 * eps], [-0.6 * eps, 0.6 * eps]],
                        eps=eps, albedo0=0.05)
    m.setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success
    assert np.abs(e.values["position"][h] - sc.positions[h]).max() < 0.1 * gr.bin_width
    assert np.all(np.abs(e.values["albedo"] - sc.albedos) < 4 * e.std["albedo"])


def test_faint_hidden_patch_is_reported_unidentifiable():
    sc, sensor = _corner((0.04, 1e-9), 1e-7)  # H2's third bounce ~1e-12 of the peak: below the noise
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=7, scene=sc, sensor=sensor)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.004, -0.003], [-0.003, 0.004]])
    m.setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    faint, bright = h[1], h[0]
    assert not e.identifiable["albedo"][faint] and not e.identifiable["position"][faint]
    assert e.identifiable["albedo"][bright] and e.identifiable["position"][bright]
    assert abs(e.values["albedo"][bright] - sc.albedos[bright]) < 4 * e.std["albedo"][bright]
    recs = patch_records(e, np.arange(4), ~sc.hidden, m.names)
    pf = recs[faint]
    assert pf["albedo"] is None and "albedo" in pf["unidentifiable"] and pf["position"] is None
    assert "identifiability limit" in pf["notes"]["albedo"] or "null direction" in pf["notes"]["albedo"]


def test_failed_solves_raise_or_are_flagged():
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=1)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.01, -0.01], [-0.01, 0.01]])
    m.setup()
    st = quiet()
    st.ipopt.max_iter = 2
    with pytest.raises(SolverError) as ei:
        fit_model(m, cap.stir, st, noise=cap.noise)
    assert ei.value.status == "Maximum_Iterations_Exceeded"
    st.ipopt.raise_on_failure = False
    e = fit_model(m, cap.stir, st, noise=cap.noise)
    assert not e.success and e.flags[0].startswith("FAILED")
    st = quiet()
    st.lm.max_nfev = 1
    with pytest.raises(SolverError):
        solve_lm(JointNLP(m, cap.stir, st, noise=cap.noise))


@pytest.mark.parametrize("mutate,match", [
    (lambda s: setattr(s, "solver", "newton"), "solver must be one of"),
    (lambda s: setattr(s.cost, "cost", "mle"), "cost must be one of"),
    (lambda s: setattr(s.cost, "tikhonov", -1.0), "tikhonov must be"),
    (lambda s: setattr(s.ipopt, "hessian", "bfgs"), "hessian must be one of"),
    (lambda s: setattr(s.lm, "jacobian", "complex-step"), "jacobian must be one of"),
    (lambda s: (setattr(s.cost, "cost", "pem"), setattr(s.cost, "likelihood", "poisson")), "cannot be combined"),
])
def test_settings_validation(mutate, match):
    s = EstimateSettings()
    mutate(s)
    with pytest.raises(ModelError, match=match):
        s.validate()


def test_poisson_needs_poisson_capture_and_lm_needs_gaussian_oem():
    sc, gr, se, tr, cap = capture_of(three_patch, seed=1)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo").setup()
    st = quiet()
    st.cost.likelihood = "poisson"
    with pytest.raises(ModelError, match="Poisson noise attributes"):
        JointNLP(m, cap.stir, st, noise=cap.noise)
    st = quiet()
    st.cost.cost = "pem"
    with pytest.raises(ModelError, match="Gaussian output-error"):
        solve_lm(JointNLP(m, cap.stir, st, noise=cap.noise))
    with pytest.raises(ModelError, match="expects"):
        JointNLP(m, cap.stir[:, :, :10], quiet())
