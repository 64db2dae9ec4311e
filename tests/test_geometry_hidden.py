"""Hidden patches: T3 distances within eps (hidden corner), 1/2/4 hidden patches behind a wall,
paper labeling vs robust labeling, ambiguity flags, hard cases."""
import numpy as np
import pytest

from stircasadi.brdf import Lambertian
from stircasadi.geometry import estimate_geometry
from stircasadi.geometry.estimate import GeometrySettings
from stircasadi.problem import load_problem
from stircasadi.scene import Patch, Scene
from stircasadi.irf import GaussianIRF
from stircasadi.sensor import GaussianNoise, Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import simulate

HID = [(0.45, -0.15, 0.75), (-0.40, 0.20, 0.70), (0.05, 0.35, 0.65), (-0.2, -0.3, 0.8)]


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def wall_scene(n_hidden, hidden_pos=HID):
    wall = [Patch((x, y, 1.2), (0, 0, -1.0), 0.01, Lambertian(0.7))
            for x in (-0.3, 0, 0.3) for y in (-0.25, 0, 0.25)]
    hid = [Patch(c, tuple(_unit(np.array([0, 0, 1.2]) - np.array(c))), 0.04, Lambertian(0.6), hidden=True)
           for c in hidden_pos[:n_hidden]]
    return Scene(wall + hid)


def capture_of(sc, rel=1e-7, seed=0):
    se = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(relative=rel))
    cap = se.capture(simulate(sc, TimeGrid(0, 0.005, 1024), sensor=se), seed=seed)
    cap.observed_xyz = sc.positions[cap.obs_ids()]  # relay-wall style: the wall points are known
    cap.illuminated_xyz = sc.positions[cap.ill_ids()]
    return cap


def errors(est, sc):
    T = sc.positions[sc.hidden]
    return np.array([np.min(np.linalg.norm(T - h, axis=1)) for h in est.positions[~est.visible]])


def test_hidden_corner_distances_within_eps():
    mod = load_problem("hidden_corner")
    sc, g, se = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    est = estimate_geometry(se.capture(simulate(sc, g, sensor=se), seed=0), hidden=2)
    true = np.linalg.norm(sc.positions[2:, None] - sc.positions[None, :2], axis=2)
    got = np.array([b["distances"] for b in est.hidden_distance_bounds])
    eps = np.array([b["eps"] for b in est.hidden_distance_bounds])
    # match estimated hidden patches to the true ones
    order = [int(np.argmin(np.abs(true - g_).sum(axis=1))) for g_ in got]
    assert sorted(order) == [0, 1]
    assert np.all(np.abs(got - true[order]) <= eps)
    assert any(a["kind"] == "underdetermined" for a in est.ambiguities)  # 2 anchors: a circle


@pytest.mark.parametrize("n_hidden", [1, 2, 4])
def test_hidden_patches_recovered(n_hidden):
    sc = wall_scene(n_hidden)
    est = estimate_geometry(capture_of(sc), hidden=n_hidden)
    e = errors(est, sc)
    assert len(e) == n_hidden
    if n_hidden <= 2:
        assert e.max() < 1e-3
        # the placed patches explain every hidden-only return
        assert est.stats["hidden"].extra["n_traces_unexplained"] == 0
        assert est.stats["hidden"].extra["n_traces_hidden_only_returns"] > 0
    else:  # merged onsets bias two of the four by ~2 cm (measured 16 and 22 mm)
        assert np.sort(e)[1] < 1e-3 and e.max() < 0.04
    assert any(a["kind"] == "mirror" for a in est.ambiguities)  # coplanar wall: reported


def test_paper_labeling_fails_where_robust_holds():
    sc = wall_scene(2)
    cap = capture_of(sc)
    paper = estimate_geometry(cap, hidden=2, settings=GeometrySettings(hidden_method="paper"))
    robust = estimate_geometry(cap, hidden=2)
    assert errors(paper, sc).max() > 0.1
    assert errors(robust, sc).max() < 1e-3


def test_hidden_patch_near_visible_plane_and_low_snr_stay_finite():
    sc = wall_scene(1, [(0.1, 0.05, 1.1)])  # 10 cm from the wall plane
    est = estimate_geometry(capture_of(sc, rel=1e-6), hidden=1)
    assert np.all(np.isfinite(est.positions))
    e = errors(est, sc)
    # either recovered, or reported missing -- never silently wrong
    assert (len(e) == 1 and e[0] < 0.02) or any(a["kind"] == "missing" for a in est.ambiguities)
    # low SNR: finite output, onsets missing rather than invented
    sc = wall_scene(1)
    est = estimate_geometry(capture_of(sc, rel=3e-3), hidden=1)
    assert np.all(np.isfinite(est.positions[est.visible]))


@pytest.mark.parametrize("pos, rel, recovered", [
    ((0.2, -0.1, 1.15), 1e-7, True),    # measured error 2.7e-5 m
    ((0.0, 0.0, 1.15), 1e-7, None),     # measured 1.2 mm (mirror-ambiguous, flagged)
    ((0.1, 0.05, 1.15), 1e-6, None),    # third onset merged with the wall's: reported missing
])
def test_hidden_patch_5cm_from_visible_plane(pos, rel, recovered):
    """5 cm in front of the wall: the hidden return nearly coincides with the wall's own later
    families. Finite output, and the patch is either placed within 2 cm or reported missing."""
    sc = wall_scene(1, [pos])
    est = estimate_geometry(capture_of(sc, rel=rel), hidden=1)
    assert np.all(np.isfinite(est.positions))
    e = errors(est, sc)
    kinds = {a["kind"] for a in est.ambiguities}
    assert (len(e) == 1 and e[0] < 0.02) or "missing" in kinds
    if recovered:
        assert len(e) == 1 and e[0] < 1e-4, e


@pytest.mark.parametrize("seed", range(6))
def test_three_patch_at_5db_snr(seed):
    """SNR 5 dB on the weakest second bounce (noise std = its peak / 10^(5/20)). Measured on seeds
    0-5: 1-3 of the 3 distances detected; every detected distance inside its eps; with all three,
    RMSE 1.9 mm. Finite output, and either all distances with RMSE within the largest eps, or the
    missing ones left unknown and the embedding flagged underdetermined."""
    from stircasadi.report import position_rmse

    mod = load_problem("three_patch")
    sc, g = mod.build_scene(), mod.build_grid()
    irf = GaussianIRF.from_ps(210.0)
    tr = simulate(sc, g, sensor=Sensor(irf=irf))
    off = ~np.eye(3, dtype=bool)
    peak2 = Sensor(irf=irf).capture(tr, seed=0).stir.max(axis=2)[off].min()  # noiseless, IRF-blurred
    sigma = peak2 / 10 ** (5 / 20)
    cap = Sensor(irf=irf, noise=GaussianNoise(sigma=sigma)).capture(tr, seed=seed)
    est = estimate_geometry(cap, hidden=0)
    assert np.all(np.isfinite(est.positions))
    fin = np.isfinite(est.distances) & off
    assert fin.sum() >= 2  # at least one pair (both directions)
    assert np.all(np.abs(est.distances - sc.distances)[fin] <= est.eps[fin])
    assert np.all(np.isinf(est.eps[off & ~fin]))
    if fin.sum() == 6:
        assert position_rmse(est, cap.truth)[0] <= est.eps[off].max()
    else:
        assert any(a["kind"] == "underdetermined-embedding" for a in est.ambiguities)
