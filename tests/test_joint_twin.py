"""Twin experiments: simulate known values, estimate them back (IPOPT exact / GN, LM AD / FD)."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.problems import glossy_patch, hidden_corner, lambertian_walls, three_patch
from stircasadi.joint import JointNLP
from stircasadi.joint.fit import fit_model
from stircasadi.model import TransientModel
from stircasadi.irf import GaussianIRF
from stircasadi.sensor import PoissonNoise, Sensor

from _legacy_scenes import three_patch_right_angle
from _reflectance_helpers import capture_of, hidden_model, quiet


@pytest.mark.parametrize("n", [10, 30])
def test_lambertian_albedos_within_two_sigma_at_one_percent_noise(n):
    sc, gr, se, tr, cap = capture_of(lambertian_walls, seed=11, n_patches=n)
    assert cap.noise["model"] == "gaussian"
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", "all", initial=0.5).setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success and e.iterations < 30
    z = (e.values["albedo"] - sc.albedos) / e.std["albedo"]
    assert np.mean(np.abs(z) <= 2.0) >= 0.8, z
    assert np.all(np.abs(z) < 4.0), z
    assert np.all(e.std["albedo"] < 0.02)


def test_phong_parameters_of_a_glossy_patch():
    sc, gr, se, tr, cap = capture_of(glossy_patch, seed=5, sensor=glossy_patch.build_sensor(1e-4))
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", "all", initial=0.5)
    m.set_unknown("specular", "glossy", initial=0.2).set_unknown("exponent", "glossy", initial=20.0, upper=200.0)
    m.setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success
    g = 0
    for name, true in (("albedo", 0.3), ("specular", 0.5), ("exponent", 8.0)):
        v, s = e.values[name][g], e.std[name][g]
        assert e.identifiable[name][g]
        assert abs(v - true) < 3.5 * s, (name, v, s)
    assert e.std["specular"][g] < 0.1 and e.std["exponent"][g] < 3.0
    assert e.values["albedo"][g] + e.values["specular"][g] <= 1.0 + 1e-9


def _dist(pos, sc, h):
    """Distances of the hidden positions ``pos[h]`` to the two visible patches (the paper's T3)."""
    vis = np.flatnonzero(~sc.hidden)
    return np.linalg.norm(pos[h][:, None, :] - sc.positions[vis][None], axis=2)


def test_hidden_corner_joint_geometry_and_albedo():
    """Fig. 12: hidden positions start 1.2 cm (2.4 bins) off in the plane, noise 1e-6 of the peak."""
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=4)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.012, -0.009], [-0.011, 0.012]])
    m.setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success and e.iterations <= 40
    derr = (_dist(e.values["position"], sc, h) - _dist(sc.positions, sc, h)) / gr.bin_width
    assert np.abs(derr).max() < 0.05, derr
    zp = (e.values["position"][h] - sc.positions[h])[:, [0, 2]] / e.std["position"][h][:, [0, 2]]
    assert np.all(np.abs(zp) < 4.0), zp
    za = (e.values["albedo"] - sc.albedos) / e.std["albedo"]
    assert np.all(np.abs(za) < 4.0), za
    assert np.linalg.norm(e.values["position"][h] - sc.positions[h], axis=1).max() < 1e-3


def test_hidden_corner_noise_free_beats_the_probe_floor():
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=0, sensor=Sensor(irf=hidden_corner.build_sensor().irf))
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.012, -0.009], [-0.011, 0.012]])
    m.setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    derr = np.abs(_dist(e.values["position"], sc, h) - _dist(sc.positions, sc, h)) / gr.bin_width
    assert derr.max() < 2e-4, derr  # the exact frequency-domain delay's floor: 2e-4 bin
    assert np.abs(e.values["albedo"] - sc.albedos).max() < 1e-5


def test_hessian_variants_and_lm_agree():
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=4)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.006, -0.004], [-0.005, 0.006]])
    m.setup()
    out = {}
    for hess in ("exact", "gauss-newton"):
        st = quiet()
        st.ipopt.hessian = hess
        out[hess] = fit_model(m, cap.stir, st, noise=cap.noise)
    for jac in ("ad", "fd"):
        st = quiet(solver="lm")
        st.lm.jacobian = jac
        out["lm-" + jac] = fit_model(m, cap.stir, st, noise=cap.noise)
    ref = out["exact"]
    for k, e in out.items():
        assert e.success, k
        d = np.abs(e.values["position"][h] - ref.values["position"][h]).max()
        assert d < 0.05 * ref.std["position"][h].max(), (k, d)
    st = quiet()
    st.ipopt.hessian = "limited-memory"
    st.ipopt.max_iter = 40
    st.ipopt.raise_on_failure = False
    lb = fit_model(m, cap.stir, st, noise=cap.noise)
    assert lb.iterations > ref.iterations  # exact second derivatives pay off


def test_pem_on_white_noise_reduces_to_oem():
    sc, gr, se, tr, cap = capture_of(three_patch, seed=9)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    oem = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    st = quiet()
    st.cost.cost = "pem"
    pem = fit_model(m, cap.stir, st, noise=cap.noise)
    assert abs(pem.extra["ar1"]) < 0.1
    assert np.all(np.abs(pem.values["albedo"] - oem.values["albedo"]) < 2 * oem.std["albedo"])


def test_pem_whitens_correlated_noise():
    """AR(1) noise (a = 0.8): PEM estimates a and gives honest intervals where OEM is overconfident."""
    sc, gr, se, tr, _ = capture_of(three_patch, seed=0, scene=three_patch_right_angle())
    rng = np.random.default_rng(21)
    s = 2e-3 * tr.stir.max()
    e = np.zeros_like(tr.stir)
    v = rng.normal(0, s * np.sqrt(1 - 0.64), tr.stir.shape)
    e[..., 0] = rng.normal(0, s, tr.stir.shape[:2])
    for k in range(1, gr.n_bins):
        e[..., k] = 0.8 * e[..., k - 1] + v[..., k]
    y = tr.stir + e
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    st = quiet()
    st.cost.cost = "pem"
    pem = fit_model(m, y, st, noise={"model": "gaussian", "sigma": s})
    assert abs(pem.extra["ar1"] - 0.8) < 0.05
    assert np.all(np.abs(pem.values["albedo"] - sc.albedos) < 4 * pem.std["albedo"])


def test_poisson_likelihood_recovers_albedos():
    sensor = Sensor(irf=GaussianIRF.from_ps(60.0), noise=PoissonNoise(photons=2e4))
    sc, gr, se, tr, cap = capture_of(lambertian_walls, seed=2, sensor=sensor, n_patches=10)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    st = quiet()
    st.cost.likelihood = "poisson"
    e = fit_model(m, cap.stir, st, noise=cap.noise)
    z = (e.values["albedo"] - sc.albedos) / e.std["albedo"]
    assert e.success and np.all(np.abs(z) < 4), z


def test_tikhonov_shrinks_toward_zero():
    sc, gr, se, tr, cap = capture_of(three_patch, seed=1)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    free = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    st = quiet()
    st.cost.tikhonov = 1e7
    reg = fit_model(m, cap.stir, st, noise=cap.noise)
    assert np.all(reg.values["albedo"] < free.values["albedo"])


def test_folded_residuals_are_exact():
    """The per-trace QR fold changes neither the optimum, nor the cost, nor the Fisher intervals."""
    sc, gr, se, tr, cap = capture_of(lambertian_walls, seed=12, n_patches=10)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    st = quiet()
    folded = JointNLP(m, cap.stir, st, noise=cap.noise)
    st2 = quiet()
    st2.cost.fold = False
    plain = JointNLP(m, cap.stir, st2, noise=cap.noise)
    assert folded.r.shape[0] < plain.r.shape[0] / 10
    x = m.x0 + 0.1
    assert abs(float(folded.f_cost(x)) - float(plain.f_cost(x))) < 1e-9 * float(plain.f_cost(x))
    Jf, Jp = folded.jacobian(x), plain.jacobian(x)
    assert np.allclose(Jf.T @ Jf, Jp.T @ Jp, rtol=1e-10)
    ef, ep = fit_model(m, cap.stir, st, noise=cap.noise), fit_model(m, cap.stir, st2, noise=cap.noise)
    assert np.allclose(ef.values["albedo"], ep.values["albedo"], atol=1e-9)
    assert np.allclose(ef.std["albedo"], ep.std["albedo"], rtol=1e-8)
    assert abs(ef.extra["cost"] - ep.extra["cost"]) < 1e-6 * ep.extra["cost"]


def test_probe_scene_nine_patches_one_hidden_position():
    """The nine-patch scene (9 patches, 1 hidden, 160 bins, noise-free): a frequency-domain delay's floor is 2e-4 bin with an
    exact frequency-domain delay, and L-BFGS ran out at 300 iterations."""
    from stircasadi.problems import nine_patch_hidden as nine

    sc, gr, se, tr, cap = capture_of(nine, seed=0)
    h = 8
    p0 = sc.positions[h] + np.array([0.008, -0.006, 0.007])
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5)
    m.set_unknown("position", [h], initial=p0, lower=-0.03, upper=0.03, scale=0.03).setup()
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success and e.iterations <= 25
    d_est = np.linalg.norm(e.values["position"][h] - sc.positions[:8], axis=1)
    d_true = np.linalg.norm(sc.positions[h] - sc.positions[:8], axis=1)
    assert np.abs(d_est - d_true).max() / gr.bin_width < 1e-6
    assert np.abs(e.values["albedo"] - sc.albedos).max() < 1e-8


def test_warm_start_reconverges_quickly():
    sc, gr, se, tr, cap = capture_of(hidden_corner, seed=4)
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.012, -0.009], [-0.011, 0.012]])
    m.setup()
    cold = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    cap2 = se.capture(tr, seed=5)  # a new frame of the same scene
    warm = fit_model(m, cap2.stir, quiet(), noise=cap2.noise, warm=cold)
    assert warm.success and warm.iterations < cold.iterations
    d = _dist(warm.values["position"], sc, h) - _dist(sc.positions, sc, h)
    assert np.abs(d).max() < 0.05 * gr.bin_width
