"""The surface fit judged on seeded random twins (``stircasadi.testing.surfaces``), and the edge
map that marks where its std do not hold the model's error.

The study itself is ``benchmarks/surface_coverage.py`` (BENCHMARKS.md, "Surface fit on seeded
twins"); here: the generator is deterministic and renders the support it reports, the edge rule
on hand-made masks, and a few scenes of the study must not end SILENT-WRONG."""
import sys
from pathlib import Path

import numpy as np
import pytest

from stircasadi.nlos.surface.mask import edge_map as _edge
from stircasadi.testing.surfaces import TWIN_KINDS, random_surface_twin

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))


def test_edge_marks_cut_cells_and_their_neighbours():
    """A 4 x 4 block of full cells (albedo 0.5) inside a ring of partly covered ones (0.1) on an
    8 x 8 grid: the ring and the block's outer ring are edge, the 2 x 2 core is not; two rings
    from the outside are edge whatever the albedo (a cut cell may hold most of its area); an
    empty mask has no edge."""
    mask = np.zeros((8, 8), bool)
    mask[1:7, 1:7] = True
    rho = np.where(mask, 0.1, 0.0)
    rho[2:6, 2:6] = 0.5
    e = _edge(mask, rho)
    core = np.zeros((8, 8), bool)
    core[3:5, 3:5] = True
    assert np.array_equal(e, mask & ~core)
    full = np.ones((5, 5), bool)
    e2 = _edge(full, np.full((5, 5), 0.4))
    inner = np.zeros((5, 5), bool)
    inner[2, 2] = True               # two rings from the grid's border: a border cell may be cut
    assert np.array_equal(e2, ~inner)
    bar = np.zeros((6, 8), bool)
    bar[1:5, 1:7] = True             # a bar four cells wide at a uniform albedo: its two middle rows
    e3 = _edge(bar, np.where(bar, 0.8, 0.0))     # are two cells from the outside, still edge
    assert np.array_equal(e3, bar)
    assert not _edge(np.zeros((4, 4), bool), np.zeros((4, 4))).any()


def test_random_twin_is_seeded_and_renders_its_support():
    a, ta, da = random_surface_twin(17)
    b, tb, db = random_surface_twin(17)
    c, _, dc = random_surface_twin(18)
    assert da == db and np.array_equal(a.traces, b.traces) and dc != da
    assert ta["kind"] in TWIN_KINDS and 0.3 <= ta["albedo"] <= 0.9
    assert a.traces.shape != c.traces.shape or not np.allclose(a.traces, c.traces)
    # the support reported is the one rendered: sampled at the 1 cm patch centres it counts the
    # drawn patches, and a patch's neighbourhood inside its square maps to the same patch
    lin = np.linspace(-0.15, 0.15, 31)[:-1] + 0.005
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    on = ta["support_fn"](xx, yy)
    assert on.sum() > 20
    assert np.array_equal(on, ta["support_fn"](xx + 0.0049, yy - 0.0049))
    assert not ta["support_fn"](np.array([0.2]), np.array([0.0]))[0]      # outside the rendered square


@pytest.mark.slow
@pytest.mark.parametrize("seed", [8, 11, 14])
def test_study_scenes_are_not_silent_wrong(seed):
    """Scenes of the study (seeds 8 and 14 ended SILENT-WRONG before the edge map: full cells
    beside partly covered ones at 3-8 std in albedo; 11 was OK): each fit is OK or FLAGGED by
    the study's rule, and an OK fit's claims (its full nodes not marked edge) hold no error
    beyond 4 std."""
    from surface_coverage import run_one

    r = run_one(seed, 12, 2, "none")
    assert r["verdict"] in ("OK", "FLAGGED"), r
    if r["verdict"] == "OK":
        assert r["beyond4"] == 0 and r["mask_off_support"] <= 0.1 * max(r["mask_nodes"], 1)


@pytest.mark.slow
def test_a_tilted_square_with_cut_cells_is_covered_by_its_std():
    """Seed 310 of ``benchmarks/surface_coverage.py`` (a square tilted 20.5 deg, paired relay,
    0.31 % noise) was SILENT-WRONG: 16 of 38 claims beyond 2 std, depths alternating row by row
    (+-0.7 mm at 0.2 mm std) over the whole square because the cells its edges cut were modelled
    as uniform. With their centroids fitted (kept by the likelihood ratio): chi2/dof within
    1 +- 0.01, the claims within 2 std at the binomial test's rate, none beyond 4 std, and the
    depth error halved (0.55 -> 0.33 mm, measured; asserted below 0.45 mm)."""
    from surface_coverage import run_one

    r = run_one(310, 12, 2, "none")
    assert r["cut_cells"] > 0
    assert abs(r["chi2_dof"] - 1.0) < 0.01
    assert r["verdict"] == "OK", r
    assert r["beyond4"] == 0 and r["coverage2"] >= 0.9
    assert r["depth_mae"] < 0.45e-3


@pytest.mark.slow
def test_two_bars_at_two_depths_get_a_height_field_each():
    """Seed 513 of ``benchmarks/surface_coverage.py`` (two bars 11.3 cm apart in depth, one node
    between them on the 12 x 12 grid, confocal, 0.75 % noise). One height field: the node between
    them enters both bars' central differences and tilts their normals (median 13.8 deg measured,
    asserted above 5) and the fit fails by the depth-step check or its iteration limit. Split
    (step 4a, ``steps.py``): two labels kept, median normal error 0.39 deg, depth MAE 0.43 mm,
    albedo MAE 0.039 (measured; asserted below 1.5 deg, 1 mm, 0.1), no depth-step reason, and
    the verdict is never SILENT-WRONG."""
    from surface_coverage import run_one

    one = run_one(513, 12, 2, "none", split_steps=False)
    assert one["split"] == 0 and one["normal_deg_median"] > 5.0 and not one["success"]
    r = run_one(513, 12, 2, "none")
    assert r["split"] == 2
    assert r["normal_deg_median"] < 1.5 and r["depth_mae"] < 1e-3 and r["albedo_mae"] < 0.1
    assert not any("side by side" in x for x in r["reasons"])
    assert r["verdict"] in ("OK", "FLAGGED"), r


def test_edge_std_widens_the_edge_nodes_only_by_their_floors():
    """Hand-worked with the calibrated constants (factor 1; floors 0.01 x the pitch in depth, in
    albedo the larger of 0.05 x the bright albedo (0.25 under the albedo prior) and the node's
    departure from its mask neighbours' mean): a 3 x 3 mask, its ring marked edge, the centre
    not. Cell pitch 25 mm, every depth std 1 mm, albedo std 0.01, albedos 0.5. An edge node's
    depth std is hypot(1 mm, 0.25 mm) = 1.030776 mm, its albedo std hypot(0.01, 0.025) = 0.026926
    (uniform albedos: no departure), under the prior hypot(0.01, 0.125) = 0.125399; its normal
    std grows by the depth's ratio; the centre keeps its std, and the inputs are not changed in
    place. One corner at 0.8: bright albedo (90th percentile of eight 0.5 and one 0.8) 0.56, the
    corner's neighbourhood mean (0.8 + 3 x 0.5) / 4 = 0.575, its floor the departure 0.225. With
    no edge node nothing changes; factor 1 and no floors give the Fisher std back."""
    from stircasadi.nlos.surface.mask import edge_std

    edge = np.ones((3, 3), bool)
    edge[1, 1] = False
    mask = np.ones((3, 3), bool)
    z_std, rho_std = np.full(9, 1e-3), np.full(9, 0.01)
    n_std = np.tile([0.01, 0.02, 0.001], (9, 1))
    rho = np.full(9, 0.5)
    z2, r2, n2 = edge_std(edge, mask, z_std, rho, rho_std, n_std, 0.025)
    e = edge.ravel()
    assert np.allclose(z2[e], 1.030776e-3, rtol=1e-6) and np.isclose(z2[4], 1e-3)
    assert np.allclose(r2[e], 0.0269258, rtol=1e-6) and np.isclose(r2[4], 0.01)
    assert np.allclose(n2[e], n_std[e] * 1.030776, rtol=1e-6) and np.allclose(n2[4], n_std[4])
    assert np.all(z_std == 1e-3) and np.all(rho_std == 0.01)            # not changed in place
    _, rp, _ = edge_std(edge, mask, z_std, rho, rho_std, n_std, 0.025, prior=True)
    assert np.allclose(rp[e], 0.1253994, rtol=1e-6) and np.isclose(rp[4], 0.01)
    z3, r3, n3 = edge_std(np.zeros((3, 3), bool), mask, z_std, rho, rho_std, n_std, 0.025)
    assert np.array_equal(z3, z_std) and np.array_equal(r3, rho_std) and np.array_equal(n3, n_std)
    rho_c = rho.copy()
    rho_c[0] = 0.8
    _, r4, _ = edge_std(edge, mask, z_std, rho_c, rho_std, n_std, 0.025)
    assert np.isclose(r4[0], np.hypot(0.01, 0.225))
    # the corner's neighbours (0, 1) and (1, 0): mean of six nodes (0.8 + 5 x 0.5) / 6 = 0.55,
    # departure 0.05 above 0.05 x 0.56 = 0.028
    assert np.isclose(r4[1], np.hypot(0.01, 0.05)) and np.isclose(r4[3], np.hypot(0.01, 0.05))
    z5, r5, n5 = edge_std(edge, mask, z_std, rho, rho_std, n_std, 0.025, factor=1.0, depth_floor=0.0,
                          albedo_floor=0.0, roughness=0.0)
    assert np.allclose(z5, z_std) and np.allclose(r5, rho_std) and np.allclose(n5, n_std)
    # the setting that switches it is a yes/no, refused otherwise with what is allowed
    from stircasadi.errors import ReconstructionError
    from stircasadi.nlos.surface import SurfaceSettings
    assert SurfaceSettings().validate().edge_std_model is True
    with pytest.raises(ReconstructionError, match="edge_std_model must be true or false"):
        SurfaceSettings(edge_std_model="maybe").validate()


def test_the_mask_under_an_albedo_prior_needs_evidence_of_its_own():
    """Hand-worked ``surface_mask`` on a 4 x 4 grid: a 2 x 2 block of albedo 0.6 in its centre,
    the ring around it at 0.1 (the albedo prior's leak beyond a surface's edge), every std 0.01
    (all significant on their own; the bright albedo, the 90th percentile of the sixteen, 0.6,
    so every node is above its tenth). Without evidence all 16 are in the mask. With each node's
    evidence (chi^2 rise without its albedo) 400 in the block, 4 on the ring (below z^2 = 9: the
    data alone do not want it) and 12 on one ring node, the mask is the block and that node."""
    from stircasadi.nlos.surface.grid import DepthGrid
    from stircasadi.nlos.surface.mask import surface_mask

    e = np.eye(3)
    grid = DepthGrid(x=np.linspace(-0.03, 0.03, 4), y=np.linspace(-0.03, 0.03, 4),
                     frame=(np.zeros(3), e[0], e[1], e[2]))
    rho = np.full((4, 4), 0.1)
    rho[1:3, 1:3] = 0.6
    std = np.full(16, 0.01)
    C = np.diag(std ** 2)
    assert surface_mask(grid, rho.ravel(), std, C, 3.0).all()
    ev = np.full((4, 4), 4.0)
    ev[1:3, 1:3] = 400.0
    ev[0, 3] = 12.0
    want = np.zeros((4, 4), bool)
    want[1:3, 1:3] = True
    want[0, 3] = True
    got = surface_mask(grid, rho.ravel(), std, C, 3.0, evidence=ev.ravel())
    assert np.array_equal(got.reshape(4, 4), want)


@pytest.mark.slow
def test_under_the_albedo_prior_the_claims_rest_on_the_data():
    """Seeds 1314 and 1308 of the study under ``prior="auto"``, two of the three SILENT-WRONG
    scenes of the held-out run 1300-1323 with the posterior's std (BENCHMARKS.md). 1314 (a
    square, paired relay, 0.57 % noise): neighbouring columns trade albedo at 2.1-2.3 of the
    posterior's std, 5 of its 28 inner numbers beyond 2 (measured); 1308 (a cap, confocal): the
    smoothing spreads albedo a node beyond the edge, 7 of its 36 mask nodes off the support. With
    ``claims_under_prior="posterior"`` both are SILENT-WRONG by the study's rule; with the
    default ("data": the data's Fisher std, and a mask node needs evidence of its own) both are
    OK. The fit itself (depths, albedos) is the same."""
    from surface_coverage import run_one

    for seed in (1314, 1308):
        post = run_one(seed, 12, 2, "auto", claims_under_prior="posterior")
        data = run_one(seed, 12, 2, "auto")
        assert post["success"] and data["success"]
        assert post["verdict"] == "SILENT-WRONG", post
        assert data["verdict"] == "OK", data
        for k in ("depth_mae", "albedo_mae", "normal_deg_median"):
            assert data[k] == post[k], (seed, k)
    assert data["mask_off_support"] <= 0.1 * data["mask_nodes"] < post["mask_off_support"], (data, post)


@pytest.mark.slow
def test_a_node_left_dark_inside_a_disk_is_not_claimed_dark():
    """Held-out seed 1423 of the study (a disk tilted 24.6 deg, confocal, 0.36 % noise, prior
    none): the fit leaves one node inside the disk at the albedo's bound 0 (truth 0.62), where its
    Fisher std (0.115, measured) made it 5.4 std off, the scene SILENT-WRONG. At a bound the
    estimate is censored and a node of zero albedo has no depth information: it is now an edge
    number (beside the mask at zero albedo, like a pruned node), its albedo std at least its
    departure from the mask neighbours' mean (about 0.6), and the scene OK."""
    from stircasadi.nlos import VolumeSettings, from_capture, lct
    from stircasadi.nlos.surface import SurfaceSettings, fit_surface
    from stircasadi.testing.surfaces import WALL_RHO, score_surface
    from surface_coverage import verdict

    cap, truth, _ = random_surface_twin(1423)
    rl = from_capture(cap)
    rl.gain[:] = (WALL_RHO / np.pi) ** 2
    res = fit_surface(rl, lct(rl, VolumeSettings(gate_m=0.2, n_lateral=16)).maps(),
                      SurfaceSettings(n_nodes=12, levels=2, known_gain=True), gate=0.2)
    sc = score_surface(res, truth, maps=True)
    dark = sc["full"] & (res.albedo <= 0.0)
    assert dark.sum() == 1 and res.edge[dark].all() and not res.mask[dark].any()
    assert np.all(np.abs(sc["albedo_z"][dark]) < 2.0) and np.all(res.albedo_std[dark] > 0.5)
    assert res.success and verdict(res.success, {k: v for k, v in sc.items() if not isinstance(v, np.ndarray)}) == "OK"


@pytest.mark.slow
def test_a_low_noise_cap_s_edge_nodes_are_covered_once_widened():
    """Seed 1107 of ``benchmarks/surface_coverage.py`` (a spherical cap of radius 0.73 m, paired
    relay, 0.9 % noise; one of the scenes the edge std were calibrated on). With the Fisher std
    alone (``edge_std_model=False``) its edge nodes held albedos 4.8 and 6.0 std off (+0.05 and
    +0.06 at std 0.011 and 0.010, measured) and a depth 3.2 std off: by the study's rule, every
    full node a claim, SILENT-WRONG. Widened (the default) the same fit is OK with no number
    beyond 4 std; nothing else of the fit changes (depths, albedos, mask, inner nodes' std)."""
    from surface_coverage import run_one

    raw = run_one(1107, 12, 2, "none", edge_std_model=False)
    r = run_one(1107, 12, 2, "none")
    assert raw["success"] and r["success"]
    assert raw["edge_beyond4"] >= 1 and raw["verdict"] == "SILENT-WRONG", raw
    assert r["edge_beyond4"] == 0 and r["beyond4"] == 0 and r["verdict"] == "OK", r
    for k in ("depth_mae", "albedo_mae", "mask_nodes", "coverage2", "n_inner"):
        assert r[k] == raw[k], k
