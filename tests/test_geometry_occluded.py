"""Fig. 13 (three planes, the left panel hidden by a screen): the visible structure from second
onsets, robust to second onsets replaced by an earlier family (a return via a hidden patch)."""
import numpy as np
import pytest

from stircasadi.geometry import estimate_geometry
from stircasadi.report import position_rmse
from stircasadi.problem import load_problem
from stircasadi.transport import simulate

# Visible RMSE after Procrustes at the problem's noise (GaussianNoise relative 1e-6), measured on
# seeds 0-6: 0.18-0.23 mm (seed 0: 0.20 mm; `python benchmarks/geometry.py occluded`). The bound
# is twice the worst seed. (Before the refinement's bounds were made to hold jointly: 0.18-0.77 mm.)
RMSE_BOUND = 5.0e-4


@pytest.fixture(scope="module")
def occluded():
    mod = load_problem("three_planes_occluded")
    sc, g, se = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    return sc, se, simulate(sc, g, sensor=se)


def test_visible_structure_at_problem_noise(occluded):
    sc, se, tr = occluded
    cap = se.capture(tr, seed=0)
    est = estimate_geometry(cap, hidden=0)
    assert est.success and est.frame == "source-origin"
    assert set(est.ids[est.visible].tolist()) == set(np.flatnonzero(~sc.hidden).tolist())
    rmse, _, _ = position_rmse(est, cap.truth)
    assert rmse < RMSE_BOUND, rmse
    assert est.stats["refine"].extra["widen"] == 1.0


def test_earlier_family_in_both_directions_is_dropped(occluded):
    """Twin experiment: in 8 visible wall/right-panel pairs an earlier copy of the second bounce
    (6 cm of path early, in both O2_ij and O2_ji so reciprocity holds) stands in for a return via
    the hidden panel. With the outlier screen exactly these 8 pairs are dropped and the RMSE is
    that of the clean capture (0.20 mm); without it the bounds must be widened x4 (0.21 mm; it
    was 11 mm before the bounds were made to hold jointly)."""
    sc, se, tr = occluded
    cap = se.capture(tr, seed=0)
    ill, obs = cap.ill_ids(), cap.obs_ids()
    rng = np.random.default_rng(5)
    wall, right = ill[ill < 49], ill[ill >= 98]
    pairs = {(int(a), int(b)) for a, b in zip(rng.choice(wall, 8, replace=False),
                                              rng.choice(right, 8, replace=False))}
    for a, b in pairs:
        for i, j in ((a, b), (b, a)):
            x, y = int(np.flatnonzero(ill == i)[0]), int(np.flatnonzero(obs == j)[0])
            cap.stir[x, y] = cap.stir[x, y] + np.roll(cap.stir[x, y], -6)  # 6 bins = 6 cm early
    est = estimate_geometry(cap, hidden=0)
    rmse, _, _ = position_rmse(est, cap.truth)
    assert rmse < RMSE_BOUND, rmse
    flagged = [a for a in est.ambiguities if a["kind"] == "outlier-distances"]
    assert len(flagged) == 1
    assert {tuple(sorted(p)) for p in flagged[0]["pairs"]} == pairs
    for a, b in pairs:  # reported unknown, not kept with a bound they violate
        k, m = int(np.flatnonzero(est.ids == a)[0]), int(np.flatnonzero(est.ids == b)[0])
        assert np.isnan(est.distances[k, m]) and np.isinf(est.eps[k, m])


def test_hidden_panel_below_noise_is_not_invented(occluded):
    """At relative noise 1e-6 the traces that would carry the hidden panel's returns (same-plane
    pairs) peak at < 1 noise std in the noiseless capture (median 0.24, max 0.82): the default
    pipeline must place no hidden patch and keep the visible structure."""
    sc, se, tr = occluded
    cap = se.capture(tr, seed=0)
    est = estimate_geometry(cap)  # hidden=None: as many as the data support
    assert int((~est.visible).sum()) == 0
    assert est.stats["hidden"].extra["n_traces_hidden_only_returns"] == 0
    assert not any(a["kind"] == "unexplained-hidden-returns" for a in est.ambiguities)
    assert np.all(np.isfinite(est.positions))
    assert position_rmse(est, cap.truth)[0] < RMSE_BOUND


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_visible_structure_at_low_noise_where_intruders_are_detected(occluded, seed):
    """At relative noise 1e-7 the same-plane traces (no second bounce: coplanar patches) show
    their earliest third-bounce family above the detection threshold, so ~30 % of the
    second onsets are intruders, 1-3 m of path late. Before the SNR-seeded screen the RMSE on
    seeds 1 and 2 was 0.44 m and 15 mm. Measured now: 0.020 / 0.023 / 0.024 mm (seeds 0-6:
    0.020-0.034 mm). The intruders' SNR (< 9) and the true second bounces' (> 85) are two
    populations: the strong ones seed the embedding and every weak distance that disagrees is
    dropped. Seed 3 also needs the multi-start completion of ``embedding.embed``: from the
    right-angle guess of the missing (coplanar) distances the seed fit stuck at 0.33 m."""
    from stircasadi.irf import GaussianIRF
    from stircasadi.sensor import GaussianNoise, Sensor

    sc, _, tr = occluded
    se = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(relative=1e-7))
    cap = se.capture(tr, seed=seed)
    est = estimate_geometry(cap, hidden=0)
    rmse, _, _ = position_rmse(est, cap.truth)
    assert rmse < 1e-4, rmse
    split = est.stats["snr_split"].extra
    assert 9.0 < split["threshold"] < 85.0
    # every distance left is a true second bounce: coplanar pairs (no transfer) are all unknown
    lab = np.repeat(np.arange(3), 49)[est.ids]
    same = (lab[:, None] == lab[None, :]) & ~np.eye(len(lab), dtype=bool)
    assert np.all(np.isnan(est.distances[same]))
    D = np.linalg.norm(cap.truth["positions"][est.ids][:, None] - cap.truth["positions"][est.ids][None], axis=2)
    known = np.isfinite(est.distances) & ~np.eye(len(lab), dtype=bool)
    assert known.sum() == 2 * 49 * 49  # every wall/right-panel pair kept
    assert np.max(np.abs(est.distances[known] - D[known])) < 1e-3


def test_refinement_bounds_hold_jointly(occluded):
    """With ~4 900 bounded distances at 99 % each, ~24 bounds exclude the truth (~49 expected
    outside at the ML fit), so forcing every per-pair bound distorts the positions: seed 1
    measured 0.77 mm (per-pair bounds) vs 0.23 mm (Bonferroni-widened joint bounds, the
    default; eps reported per pair stays at 99 %)."""
    from stircasadi.geometry.estimate import GeometrySettings

    sc, se, tr = occluded
    cap = se.capture(tr, seed=1)
    joint = estimate_geometry(cap, hidden=0)
    per_pair = estimate_geometry(cap, hidden=0, settings=GeometrySettings(joint_bounds=False))
    r_joint = position_rmse(joint, cap.truth)[0]
    r_pair = position_rmse(per_pair, cap.truth)[0]
    assert r_joint < RMSE_BOUND and r_joint < 0.6 * r_pair, (r_joint, r_pair)
    assert joint.stats["refine"].extra["n_outside"] == 0
    assert joint.stats["refine"].extra["bound_scale"] > 1.5
    # the reported eps are the per-pair ones (what the Monte Carlo coverage tests check)
    assert np.allclose(joint.eps[np.isfinite(joint.eps)], per_pair.eps[np.isfinite(joint.eps)])


def test_failed_family_fits_are_neither_reported_nor_subtracted(occluded):
    """Fig. 13 at noise 1e-8, every family of every trace (third_onsets, 4 per trace): a fit that
    diverges from its threshold crossing used to be reported (and subtracted) with amplitudes of
    1e11-1e18 in 102 of the 9 604 traces. Every family reported now has a positive std and an
    fitted peak height below 1.1x the STIR's peak."""
    from stircasadi.geometry import onsets as on
    from stircasadi.irf import GaussianIRF
    from stircasadi.sensor import GaussianNoise, Sensor

    _, _, tr = occluded
    cap = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(relative=1e-8)).capture(tr, seed=0)
    tmpl = on.make_template(cap)
    third = on.third_onsets(cap, tmpl, after=None, max_pulses=4)
    pulses = [p for v in third.values() for p in v]
    assert len(pulses) > 30000  # first, second and later families of 9 604 traces
    peak = float(np.max(cap.stir))
    g_peak = float(tmpl.pulse(np.zeros(1))[0][0])  # amplitude -> peak height of the fitted pulse
    assert all(np.isfinite(p["tau_std"]) and p["tau_std"] > 0 for p in pulses)
    assert max(abs(p["amplitude"]) * g_peak for p in pulses) < 1.1 * peak


def test_hidden_panel_returns_are_reported_not_labeled(occluded, monkeypatch):
    """At 1e-7 the hidden panel's returns are detected in ~1 000 traces (families after the
    first/second bounce and before every visible path of three or more bounces: only a hidden
    point can produce them) but they blend within the IRF, so no patch is placed; the estimate
    says so (``unexplained-hidden-returns``) instead of staying silent. Control: the same scene
    with the hidden panel's albedo set to 1e-9 has no such trace (also at 1e-8, measured)."""
    import stircasadi.problems.three_planes as tp
    from stircasadi.irf import GaussianIRF
    from stircasadi.sensor import GaussianNoise, Sensor
    from stircasadi.transport import simulate

    sc, _, tr = occluded
    se = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(relative=1e-7))
    est = estimate_geometry(se.capture(tr, seed=0))
    ex = est.stats["hidden"].extra
    assert int((~est.visible).sum()) == 0
    assert ex["n_traces_hidden_only_returns"] > 500 and ex["n_traces_unexplained"] == ex["n_traces_hidden_only_returns"]
    flagged = [a for a in est.ambiguities if a["kind"] == "unexplained-hidden-returns"]
    assert len(flagged) == 1 and flagged[0]["n_traces"] == ex["n_traces_unexplained"]

    orig = tp.albedos

    def dark_hidden(n=3 * tp.N_SIDE * tp.N_SIDE):
        a = orig(n).copy()
        a[sc.hidden] = 1e-9
        return a

    monkeypatch.setattr(tp, "albedos", dark_hidden)
    dark = tp.build_scene(occluded=True)
    tr0 = simulate(dark, tr.grid, sensor=se)
    est0 = estimate_geometry(se.capture(tr0, seed=0))
    assert est0.stats["hidden"].extra["n_traces_hidden_only_returns"] == 0
    assert not any(a["kind"] == "unexplained-hidden-returns" for a in est0.ambiguities)
