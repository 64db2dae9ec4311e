"""Forward model against hand-worked answers and against itself (three independent solvers)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr

from stircasadi.brdf import Lambertian, Mirror, Phong
from stircasadi.scene import Patch, Scene
from stircasadi.irf import ArrayIRF, GaussianIRF
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import (TransportSystem, build_state_space, radiosity, simulate)

SQ2 = math.sqrt(2.0)


def unit(v):
    v = np.asarray(v, float)
    return tuple(v / np.linalg.norm(v))


def two_patch_scene(rho1=0.6, rho2=0.8, a1=0.01, a2=0.02):
    """Two patches 1 m apart facing each other at 45 degrees, both seen from the origin."""
    return Scene([Patch((-0.5, 0.0, 1.0), unit((1, 0, -1)), a1, Lambertian(rho1)),
                  Patch((0.5, 0.0, 1.0), unit((-1, 0, -1)), a2, Lambertian(rho2))])


def three_patch_scene(brdf3=None):
    return Scene([Patch((0.3, 0.0, 1.0), unit((-0.3, 0, -1)), 0.01, Lambertian(0.7)),
                  Patch((-0.3, 0.1, 1.1), unit((0.4, 0, -1)), 0.01, Lambertian(0.5)),
                  Patch((0.0, -0.3, 0.9), unit((0, 0.5, -1)), 0.01, brdf3 or Lambertian(0.9))])


GRID = TimeGrid(0.0, 0.01, 600)
GAUSS = Sensor(GaussianIRF(0.063))


# --------------------------------------------------------------------------- hand-worked answers
def test_one_patch_onset_and_amplitude_ideal_sensor():
    d, a, rho = 1.2345, 0.01, 0.7
    sc = Scene([Patch((0, 0, d), (0, 0, -1), a, Lambertian(rho))])
    tr = simulate(sc, GRID, Sensor(), bounces=1)
    amp = rho / math.pi * 1.0 / a            # f * phi / a
    k = int(math.floor(2 * d / 0.01))        # the bin that contains tau = 2d
    assert tr.stir[0, 0, k] == pytest.approx(amp, rel=1e-14)
    assert np.count_nonzero(tr.stir) == 1


def test_one_patch_through_gaussian_irf_is_centred_at_exact_path_length():
    d, a, rho, fwhm = 1.00437, 0.01, 0.5, 0.063
    sc = Scene([Patch((0, 0, d), (0, 0, -1), a, Lambertian(rho))])
    tr = simulate(sc, GRID, Sensor(GaussianIRF(fwhm)), bounces=1)
    sigma = fwhm / (2 * math.sqrt(2 * math.log(2)))
    edges = GRID.edges
    expected = rho / (math.pi * a) * (ndtr((edges[1:] - 2 * d) / sigma) - ndtr((edges[:-1] - 2 * d) / sigma))
    np.testing.assert_allclose(tr.stir[0, 0], expected, rtol=1e-12, atol=1e-14)
    # no rounding bias: the centroid is the exact path length
    centroid = np.sum(tr.stir[0, 0] * GRID.centres) / tr.stir[0, 0].sum()
    assert centroid == pytest.approx(2 * d, abs=1e-9)


def test_two_patches_second_and_third_bounce_by_hand():
    rho1, rho2, a1, a2 = 0.6, 0.8, 0.01, 0.02
    sc = two_patch_scene(rho1, rho2, a1, a2)
    tr = simulate(sc, TimeGrid(0, 0.001, 6000), Sensor(), method="bounces", bounces=3, per_bounce=True)
    leg = math.sqrt(0.25 + 1.0)                    # origin to either patch
    cos = 1 / SQ2                                   # both cosines on the 1 m leg
    # second bounce 1 -> 2: (rho1/pi)(phi/a1) * a1 cos cos / 1^2 * (rho2/pi)
    amp12 = rho1 / math.pi / a1 * a1 * cos * cos * rho2 / math.pi
    k12 = int(math.floor((2 * leg + 1.0) / 0.001))
    second = tr.per_bounce[1]
    assert second[0, 1, k12] == pytest.approx(amp12, rel=1e-12)
    assert np.count_nonzero(second[0, 1]) == 1
    # reciprocity of the hand formula: 2 -> 1 has (rho2/pi)(1/a2) a2 cos cos (rho1/pi): the same
    assert second[1, 0, k12] == pytest.approx(amp12, rel=1e-12)
    # third bounce 1 -> 2 -> 1 arrives at 2 leg + 2 m
    amp121 = rho1 / math.pi / a1 * (a1 * cos * cos) * rho2 / math.pi * (a2 * cos * cos) * rho1 / math.pi
    k121 = int(math.floor((2 * leg + 2.0) / 0.001))
    assert tr.per_bounce[2][0, 0, k121] == pytest.approx(amp121, rel=1e-12)
    # first bounce by hand too
    k1 = int(math.floor(2 * leg / 0.001))
    assert tr.per_bounce[0][1, 1, k1] == pytest.approx(rho2 / math.pi / a2, rel=1e-14)


def test_phong_first_bounce_by_hand():
    # source at origin, camera elsewhere: the specular lobe evaluated at the true mirror angle
    kd, ks, n = 0.3, 0.5, 12.0
    src, cam = np.zeros(3), np.array([0.4, 0.0, 0.0])
    z = np.array([0.1, 0.0, 1.0])
    nrm = np.array([0.0, 0.0, -1.0])
    sc = Scene([Patch(tuple(z), tuple(nrm), 0.01, Phong(kd, ks, n))], source=src, camera=cam)
    tr = simulate(sc, GRID, Sensor(), bounces=1)
    w_in = (src - z) / np.linalg.norm(src - z)
    w_out = (cam - z) / np.linalg.norm(cam - z)
    r = 2 * np.dot(nrm, w_in) * nrm - w_in
    f = kd / math.pi + ks * (n + 2) / (2 * math.pi) * max(np.dot(r, w_out), 0) ** n
    assert tr.stir.sum() == pytest.approx(f / 0.01, rel=1e-12)


def test_mirror_path_by_hand():
    """Wall patches i, j symmetric about a mirror's foot: the third bounce i -> mirror -> j."""
    R, h = 0.9, 0.5
    wall_z = 1.5
    pi_ = np.array([-0.2, 0.0, wall_z])
    pj = np.array([0.2, 0.0, wall_z])
    mirror_c = np.array([0.0, 0.0, wall_z - h])
    sc = Scene([Patch(tuple(pi_), (0, 0, -1), 0.01, Lambertian(0.5)),
                Patch(tuple(pj), (0, 0, -1), 0.01, Lambertian(0.5)),
                Patch(tuple(mirror_c), (0, 0, 1), 0.02, Mirror(R))])
    assert sc.hidden.tolist() == [False, False, True]
    tr = simulate(sc, TimeGrid(0, 0.001, 6000), Sensor(), method="bounces", bounces=2)
    # image of i in the mirror plane z = wall_z - h: i' = (-0.2, 0, wall_z - 2h)
    img = np.array([-0.2, 0.0, wall_z - 2 * h])
    L = np.linalg.norm(pj - img)
    u = (pj - img) / L
    cos_i = cos_j = abs(u[2])                     # both patches have normals along -z
    amp = 0.5 / math.pi / 0.01 * R * 0.01 * cos_i * cos_j / L ** 2 * 0.5 / math.pi
    tau = np.linalg.norm(pi_) + L + np.linalg.norm(pj)
    k = int(math.floor(tau / 0.001))
    assert tr.stir[0, 1, k] == pytest.approx(amp, rel=1e-12)
    # and nothing else arrives in the cross trace (the wall patches cannot see each other)
    assert np.count_nonzero(tr.stir[0, 1]) == 1


# --------------------------------------------------------------------------- three methods agree
@pytest.mark.parametrize("K", [1, 2, 3])
def test_path_sums_and_frequency_agree_exact_delays(K):
    sc = three_patch_scene()
    a = simulate(sc, GRID, GAUSS, method="bounces", bounces=K)
    b = simulate(sc, GRID, GAUSS, method="frequency", bounces=K)
    assert np.linalg.norm(a.stir - b.stir) / np.linalg.norm(a.stir) < 1e-9


@pytest.mark.parametrize("sensor", [Sensor(), GAUSS, Sensor(ArrayIRF((0.1, 0.5, 1.0, 0.4, 0.2), 0.01))],
                         ids=["ideal", "gauss", "array"])
def test_three_methods_agree_integer_delays(sensor):
    sc = three_patch_scene()
    ss = simulate(sc, GRID, sensor, method="statespace", delay_mode="integer")
    fr = simulate(sc, GRID, sensor, method="frequency", bounces="all", delay_mode="integer")
    ps = simulate(sc, GRID, sensor, method="bounces", bounces=8, delay_mode="integer",
                  allow_truncation=True)  # all three are cut by the same grid end
    scale = np.linalg.norm(ss.stir)
    assert np.linalg.norm(ss.stir - fr.stir) / scale < 1e-9
    # 8 bounces leave out energy far below 1e-9 in this open scene
    assert ps.metadata["omitted_energy_rel"] < 1e-20
    assert np.linalg.norm(ss.stir - ps.stir) / scale < 1e-9


def test_glossy_scene_methods_agree_and_link_level_matches():
    sc = three_patch_scene(brdf3=Phong(0.4, 0.5, 8.0))
    a = simulate(sc, GRID, GAUSS, method="bounces", bounces=3)
    b = simulate(sc, GRID, GAUSS, method="frequency", bounces=3)
    assert a.metadata["glossy_terms"] is True
    assert np.linalg.norm(a.stir - b.stir) / np.linalg.norm(a.stir) < 1e-9
    c = simulate(sc, GRID, GAUSS, method="frequency", bounces="all")
    d = simulate(sc, GRID, GAUSS, method="frequency", bounces="all", link_level=True)
    assert np.linalg.norm(c.stir - d.stir) / np.linalg.norm(c.stir) < 1e-12


def test_state_space_matrices_are_the_papers_shift_registers():
    """Two patches, link-level (the paper's L_ij states): registers counted by hand."""
    sc = two_patch_scene()
    w = 0.01
    sysm = TransportSystem.build(sc, delay_mode="integer", bin_width=w, link_level=True)
    ss = build_state_space(sysm)
    leg = round(math.sqrt(1.25) / w)           # 112 bins source->patch and patch->camera
    d12 = round(1.0 / w)                       # 100 bins between the patches
    # inputs: 2 x 112; link nodes L_12, L_21: 2 x 100; camera links L_1o, L_2o: 2 x 112
    assert ss.n_states == 2 * leg + 2 * d12 + 2 * leg
    n_registers = 2 + 4
    A = ss.A.tocoo()
    shifts = np.sum((A.row == A.col + 1) & (A.data == 1.0))
    assert shifts == ss.n_states - n_registers
    assert ss.B.nnz == 2 and ss.C.nnz == 2
    # the impulse response of x[t+1] = A x + B u, y = C x: first bounce at 2*leg samples
    grid = TimeGrid(0, w, 700)
    tr = simulate(sc, grid, Sensor(), method="statespace", delay_mode="integer", link_level=True)
    assert tr.stir[0, 0, 2 * leg] == pytest.approx(0.6 / math.pi / 0.01, rel=1e-14)
    assert tr.stir[0, 1, 2 * leg + d12] == pytest.approx(0.6 * 0.8 / (2 * math.pi ** 2), rel=1e-12)


# --------------------------------------------------------------------------- physics checks
def test_reciprocity_lambertian_colocated_all_bounces():
    from stircasadi.problems import three_planes
    sc = three_planes.build_scene()
    tr = simulate(sc, three_planes.build_grid(), three_planes.build_sensor(), bounces="all")
    s = tr.stir
    assert np.max(np.abs(s - np.transpose(s, (1, 0, 2)))) / np.max(np.abs(s)) < 1e-11


def test_time_integral_equals_radiosity():
    sc = three_patch_scene()
    tr = simulate(sc, TimeGrid(0, 0.01, 2048), GAUSS, bounces="all")
    np.testing.assert_allclose(tr.stir.sum(axis=-1), radiosity(sc), rtol=1e-9)
    # high albedo, facing patches: many bounces matter
    sc2 = two_patch_scene(0.99, 0.99, 0.3, 0.3)
    tr2 = simulate(sc2, TimeGrid(0, 0.01, 4096), GAUSS, bounces="all")
    assert tr2.metadata["bounce_energy"][2] > 1e-3 * tr2.metadata["bounce_energy"][0]
    np.testing.assert_allclose(tr2.stir.sum(axis=-1), radiosity(sc2), rtol=1e-9)


def test_energy_never_created():
    """Flux leaving the patches, bounce after bounce, never exceeds the pulse energy."""
    from stircasadi.problems import three_planes
    sc = three_planes.build_scene()
    sysm = TransportSystem.build(sc)
    S0, T0, O0 = sysm.steady_matrices()
    area = sc.areas[sysm.node_patch]
    v = S0.toarray()                     # node radiances of the first bounce, per pulse
    total = np.zeros(sysm.n_ill)
    prev = None
    for _ in range(30):
        flux = (math.pi * area[:, None] * v).sum(axis=0)   # Lambertian exitance * area
        assert np.all(flux <= sc.phi * (1 + 1e-12))
        if prev is not None:
            assert np.all(flux <= prev * (1 + 1e-12))
        total += flux
        prev = flux
        v = T0 @ v
    assert np.all(total <= sc.phi)


# --------------------------------------------------------------------------- effects (DESIGN 7)
def test_only_needed_effects_and_skipping_changes_nothing_beyond_tolerance():
    import trimesh
    sc = three_patch_scene()
    base = simulate(sc, GRID, GAUSS)
    assert base.metadata["bounces"] == 2 and base.metadata["occlusion"].startswith("none")
    assert base.metadata["glossy_terms"] is False and base.metadata["irf"].startswith("gaussian")
    # an occluder far away blocks nothing: ray casting runs and changes nothing
    far = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    far.apply_translation((10, 10, 10))
    occ = Scene(sc.patches, occluders=far)
    with_rays = simulate(occ, GRID, GAUSS)
    assert with_rays.metadata["occlusion"].startswith("ray-cast")
    np.testing.assert_array_equal(with_rays.stir, base.stir)
    # a Phong patch with no specular lobe takes the Lambertian path, same answer
    sc_p = three_patch_scene(brdf3=Phong(0.9, 0.0, 10.0))
    np.testing.assert_allclose(simulate(sc_p, GRID, GAUSS).stir, base.stir, rtol=1e-13, atol=0)
    # the bounce truncation leaves out exactly the energy it reports
    full = simulate(sc, GRID, GAUSS, bounces="all")
    missing = full.stir.sum() - base.stir.sum()
    assert missing == pytest.approx(base.metadata["omitted_energy_rel"] * base.metadata["total_energy"], rel=1e-6)
    assert missing / full.stir.sum() < 1e-6
    # the ideal sensor skips the impulse response: same energy per trace
    ideal = simulate(sc, GRID, Sensor())
    np.testing.assert_allclose(ideal.stir.sum(-1), base.stir.sum(-1), rtol=1e-12)
    assert ideal.metadata["irf"] == "none"


def test_hidden_scene_calls_for_three_bounces():
    from stircasadi.problems import hidden_corner
    tr = simulate(hidden_corner.build_scene(), hidden_corner.build_grid(), hidden_corner.build_sensor())
    assert tr.metadata["bounces"] == 3
    assert tr.stir.shape[:2] == (2, 2)
    assert tr.metadata["bounce_energy"][2] > 0     # the hidden patches' third bounce is there


def test_occluder_hides_patches_and_blocks_legs():
    from stircasadi.problems import three_planes_occluded
    sc = three_planes_occluded.build_scene()
    assert sc.hidden.sum() == 49 and np.all(sc.hidden[49:98])
    # the hidden panel still exchanges light with the visible back wall
    assert sc.patch_visibility[49:98, :49].any()


def test_noise_is_seeded_and_poisson_mean_is_preserved():
    from stircasadi.sensor import GaussianNoise, PoissonNoise
    sc = three_patch_scene()
    tr = simulate(sc, GRID, GAUSS)
    s1 = Sensor(GAUSS.irf, GaussianNoise(relative=1e-3)).capture(tr, seed=3)
    s2 = Sensor(GAUSS.irf, GaussianNoise(relative=1e-3)).capture(tr, seed=3)
    np.testing.assert_array_equal(s1.stir, s2.stir)
    resid = (s1.stir - tr.stir) / (1e-3 * tr.stir.max())
    assert abs(resid.std() - 1) < 0.02 and abs(resid.mean()) < 0.02
    pc = Sensor(GAUSS.irf, PoissonNoise(1e6)).capture(tr, seed=1)
    assert pc.stir.sum() == pytest.approx(tr.stir.sum(), rel=5e-3)
    assert pc.noise["model"] == "poisson"


# --------------------------------------------------------------------------- mesh scenes
def test_scene_from_mesh_file(tmp_path):
    import trimesh
    quad = trimesh.Trimesh(vertices=[[-0.5, -0.5, 2], [0.5, -0.5, 2], [0.5, 0.5, 2], [-0.5, 0.5, 2]],
                           faces=[[0, 2, 1], [0, 3, 2]])
    path = tmp_path / "wall.obj"
    quad.export(path)
    sc = Scene.from_mesh(path, patch_size=0.2)
    assert sum(p.area for p in sc.patches) == pytest.approx(1.0, rel=1e-9)
    assert max(math.sqrt(p.area) for p in sc.patches) < 0.2
    assert np.allclose(sc.normals, [0, 0, -1])
    assert sc.visible.all()
    tr = simulate(sc, TimeGrid(0, 0.01, 700), GAUSS, bounces=1)
    assert tr.stir.shape[0] == sc.n_patches


# --------------------------------------------------------------------------- bad input
def test_bad_patches_raise_clear_errors():
    from stircasadi.errors import SceneError
    with pytest.raises(SceneError, match="area must be > 0"):
        Patch((0, 0, 1), (0, 0, -1), 0.0)
    with pytest.raises(SceneError, match="unit vector"):
        Patch((0, 0, 1), (0, 0, -2), 0.01)
    with pytest.raises(SceneError, match="finite"):
        Patch((0, float("nan"), 1), (0, 0, -1), 0.01)
    with pytest.raises(SceneError, match="same centre"):
        Scene([Patch((0, 0, 1), (0, 0, -1), 0.01), Patch((0, 0, 1), (0, 0, -1), 0.01)])


def test_grid_too_short_or_late_is_refused_not_truncated():
    from stircasadi.errors import TimeGridError
    sc = three_patch_scene()
    with pytest.raises(TimeGridError, match="n_bins >="):
        simulate(sc, TimeGrid(0, 0.01, 250), GAUSS)
    with pytest.raises(TimeGridError, match="first light arrives"):
        simulate(sc, TimeGrid(1.9, 0.01, 400), GAUSS)
    tr = simulate(sc, TimeGrid(0, 0.01, 250), GAUSS, allow_truncation=True)
    assert tr.stir.shape[-1] == 250
    with pytest.raises(TimeGridError, match="picoseconds"):
        TimeGrid(0, -3.0, 10)


def test_frequency_method_refuses_unbandlimited_sensor():
    from stircasadi.errors import TransportError
    with pytest.raises(TransportError, match="band-limited"):
        simulate(three_patch_scene(), GRID, Sensor(), method="frequency", bounces="all")


def test_energy_creating_scene_is_refused():
    from stircasadi.errors import TransportError
    # two huge facing patches very close: form factors > 1, the operator gains energy
    sc = Scene([Patch((0, 0, 1.0), (0, 0, -1), 4.0, Lambertian(1.0)),
                Patch((0, 0, 0.8), (0, 0, 1), 4.0, Lambertian(1.0))],
               source=(0.5, 0.5, 0.5))
    with pytest.warns(Warning, match="row sums exceed 1"):
        sc.check_physics()
    with pytest.raises(TransportError, match="spectral radius"):
        simulate(sc, TimeGrid(0, 0.01, 512), GAUSS, bounces="all", allow_truncation=True)


def test_blocked_and_streamed_frequency_solve_equals_in_memory(tmp_path):
    """Bounded memory: pulses in blocks, written into a memmap, give the same STIR."""
    from stircasadi.transport.frequency import frequency_solve
    sc = three_patch_scene()
    net = TransportSystem.build(sc)
    ref, _ = frequency_solve(net, GRID, GAUSS.irf, None)
    mm = np.lib.format.open_memmap(tmp_path / "stir.npy", mode="w+", dtype=float, shape=ref.shape)
    out, info = frequency_solve(net, GRID, GAUSS.irf, None, block_bytes=1.0, out=mm)
    assert info["pulse_blocks"] == 3 and out is mm
    np.testing.assert_allclose(np.asarray(mm), ref, rtol=0, atol=1e-15 * ref.max())
    tr = simulate(sc, GRID, GAUSS, bounces="all", out=np.zeros(ref.shape))
    np.testing.assert_allclose(tr.stir, ref, rtol=0, atol=1e-15 * ref.max())
