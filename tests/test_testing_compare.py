"""stircasadi.testing: frame alignment, matching and per-number errors against hand-made answers,
and the assertions' binomial tolerance against its definition."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stircasadi.report import procrustes_matrix
from stircasadi.testing import (assert_coverage, assert_within_sigma, compare, coverage_interval,
                                nominal_coverage)

RNG = np.random.default_rng(20240601)
P_TRUE = np.array([[0.3, 0.0, 1.0], [-0.3, 0.1, 1.1], [0.0, -0.3, 1.0], [0.2, 0.25, 1.3],
                   [-0.4, 0.0, 0.6], [0.1, 0.0, 0.55]])
N_TRUE = np.array([[0, 0, -1.0]] * 6)
VIS = np.array([True, True, True, True, False, False])
ALB = np.array([0.7, 0.5, 0.9, 0.6, 0.7, 0.5])
SOURCE = np.array([0.05, -0.02, 0.0])


def truth():
    return {"positions": P_TRUE, "normals": N_TRUE, "areas": np.full(6, 0.01), "albedo": ALB,
            "visible": VIS, "source_xyz": SOURCE}


def patch(pid, pos, visible=True, pos_std=(1e-3, 1e-3, 1e-3), normal=(0, 0, -1.0), albedo=None,
          albedo_std=None):
    return {"id": pid, "visible": visible, "position": list(map(float, pos)),
            "position_std": None if pos_std is None else list(pos_std), "normal": list(normal),
            "normal_std": [0.01, 0.01, 0.01], "albedo": albedo, "albedo_std": albedo_std}


def estimate(patches, frame="capture", source=(0.0, 0.0, 0.0), success=True, **kw):
    return {"format": "stircasadi.estimate", "version": 2, "frame": frame, "source_xyz": list(source),
            "patches": patches, "success": success, **kw}


def test_capture_frame_errors_and_z_are_the_hand_computed_ones():
    d = np.array([2e-3, -1e-3, 0.5e-3])
    est = estimate([patch(0, P_TRUE[0] + d, albedo=0.73, albedo_std=0.01)])
    c = compare(est, truth())
    assert np.allclose(c.rotation, np.eye(3))
    rows = {(r["quantity"], r["component"]): r for r in c.rows if r["patch_id"] == 0}
    for k, a in enumerate("xyz"):
        assert rows[("position", a)]["err"] == pytest.approx(d[k], abs=1e-15)
        assert rows[("position", a)]["z"] == pytest.approx(abs(d[k]) / 1e-3)
    assert rows[("position", "")]["err"] == pytest.approx(np.linalg.norm(d))
    assert rows[("albedo", "")]["err"] == pytest.approx(0.03)
    assert rows[("albedo", "")]["z"] == pytest.approx(3.0)
    s = c.summary()
    assert s["max_abs_z"] == pytest.approx(3.0)
    assert s["n_beyond_4sigma"] == 0 and s["n_missed"] == 2  # two hidden truths, none estimated


def random_orthogonal(reflect: bool) -> np.ndarray:
    Q, _ = np.linalg.qr(RNG.normal(size=(3, 3)))
    if (np.linalg.det(Q) < 0) != reflect:
        Q[:, 0] *= -1
    return Q


@pytest.mark.parametrize("reflect", [False, True], ids=["rotation", "reflection"])
def test_source_origin_frame_is_undone_about_the_source(reflect):
    """An estimate in a frame rotated (or mirrored) about the source, with the source at the
    origin, comes back onto the truth: the Procrustes matrix is the inverse transform."""
    R = random_orthogonal(reflect)
    rel = P_TRUE - SOURCE
    est_pos = rel @ R                     # the estimate's frame: source at the origin, rotated
    pats = [patch(i, est_pos[i], normal=N_TRUE[i] @ R) for i in range(4)]
    c = compare(estimate(pats, frame="source-origin"), truth())
    assert np.allclose(c.rotation, R.T, atol=1e-12)
    err = c.errors("position", kinds=("component",))
    assert np.max(np.abs(err)) < 1e-12
    assert np.max(np.abs(c.errors("normal", kinds=("component",)))) < 1e-12


def test_rotated_covariance_gives_the_aligned_component_std():
    R = random_orthogonal(False)
    C = np.diag([1e-6, 4e-6, 9e-6])       # std 1, 2, 3 mm along the estimate's axes
    names = [f"position[{i}].{a}" for i in range(4) for a in "xyz"]
    M = np.kron(np.eye(4), C)
    pats = [patch(i, (P_TRUE[i] - SOURCE) @ R, pos_std=None) for i in range(4)]
    c = compare(estimate(pats, frame="source-origin", covariance={"parameters": names, "matrix": M.tolist()}),
                truth())
    want = np.sqrt(np.diag(R @ C @ R.T))   # p' = p R^T: covariance R C R^T
    got = np.array([r["std"] for r in c.select("position", visible=True) if r["patch_id"] == 2])
    assert np.allclose(got, want, rtol=1e-10)


def test_hidden_patches_are_matched_one_to_one_not_greedily():
    """Greedy nearest-first in estimate order would pair e1 with the second truth (0.45 m away)
    and leave e2 1.5 m from the first; the assignment pairs them for a total of 1.05 m."""
    t4, t5 = P_TRUE[4], P_TRUE[5]
    axis = (t5 - t4) / np.linalg.norm(t5 - t4)
    L = np.linalg.norm(t5 - t4)
    e1 = t4 + 0.55 * L * axis
    e2 = t4 + 1.5 * L * axis
    pats = [patch(i, P_TRUE[i]) for i in range(4)] + [patch(17, e1, visible=False), patch(18, e2, visible=False)]
    c = compare(estimate(pats), truth())
    assert c.matches[17] == 4 and c.matches[18] == 5
    assert c.missed == [] and c.spurious == []


def test_extra_hidden_estimates_are_spurious_and_unplaced_truth_missed():
    pats = [patch(i, P_TRUE[i]) for i in range(4)] + [
        patch(20, P_TRUE[4] + 0.001, visible=False), patch(21, P_TRUE[4] + 0.5, visible=False),
        {"id": 22, "visible": False, "position": None}]
    c = compare(estimate(pats), truth())
    assert c.matches[20] == 4 and c.matches[21] == 5
    pats = pats[:5] + pats[6:]
    c = compare(estimate(pats), truth())
    assert c.missed == [5] and c.spurious == [22]


def test_numbers_without_std_are_unbounded_unless_exact():
    pats = [patch(0, P_TRUE[0] + [1e-3, 0, 0], pos_std=None), patch(1, P_TRUE[1], pos_std=None),
            patch(2, P_TRUE[2], albedo=None)]
    c = compare(estimate(pats), truth())
    z0 = [r["z"] for r in c.select("position", include_given=True) if r["patch_id"] == 0]
    assert z0[0] == math.inf and z0[1] == 0.0          # x off by 1 mm without std; y exact
    given = [r for r in c.rows if r["patch_id"] == 1 and r["quantity"] == "position"]
    assert all(r["given"] for r in given)
    assert c.summary()["n_no_std"] == 1
    assert c.finite


def test_non_finite_values_are_counted_and_fail_finiteness():
    pats = [patch(0, [float("nan"), 0.0, 1.0]), patch(1, P_TRUE[1], albedo=float("inf"), albedo_std=0.1)]
    c = compare(estimate(pats), truth())
    assert not c.finite
    assert c.summary()["n_nonfinite"] == 2


def test_flagged_estimates_and_ambiguous_patches_are_marked():
    pats = [patch(0, P_TRUE[0] + [0.05, 0, 0]), patch(1, P_TRUE[1] + [0.05, 0, 0])]
    amb = [{"kind": "mirror", "patch_ids": [1], "message": "two solutions"}]
    c = compare(estimate(pats, ambiguities=amb), truth())
    assert {r["patch_id"] for r in c.rows if r["flagged"]} == {1}
    s = c.summary()
    assert s["n_beyond_4sigma"] == 2 and s["n_beyond_4sigma_unflagged"] == 1
    c = compare(estimate(pats, success=False), truth())
    assert all(r["flagged"] for r in c.rows)


def test_truth_from_a_scene_and_from_a_capture_agree(tmp_path):
    from stircasadi.problem import load_problem
    from stircasadi.transport import simulate

    mod = load_problem("three_patch")
    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    cap = sensor.capture(simulate(scene, grid, sensor=sensor), seed=0)
    pats = [patch(i, scene.positions[i] + 1e-3, albedo=scene.albedos[i] + 0.01, albedo_std=0.01)
            for i in range(3)]
    a = compare(estimate(pats), cap)
    b = compare(estimate(pats), scene)
    assert [r["z"] for r in a.rows] == [r["z"] for r in b.rows]
    assert a.summary()["err_albedo"] == pytest.approx(0.01)
    import json

    path = tmp_path / "estimate.json"
    path.write_text(json.dumps(estimate(pats)))
    from_file = compare(path, scene).summary()
    assert all(from_file[k] == v or (v != v and from_file[k] != from_file[k]) for k, v in b.summary().items())


def test_bad_inputs_are_refused_with_the_reason(tmp_path):
    from stircasadi.errors import StircasadiError

    with pytest.raises(StircasadiError, match="frame"):
        compare(estimate([], frame="world"), truth())
    with pytest.raises(StircasadiError, match="truth dict"):
        compare(estimate([]), {"nope": 1})
    with pytest.raises(StircasadiError, match="not a file"):
        compare(tmp_path / "missing.json", truth())
    (tmp_path / "bad.json").write_text("{")
    with pytest.raises(StircasadiError, match="not valid JSON"):
        compare(tmp_path / "bad.json", truth())


def test_procrustes_ignores_rows_with_nan():
    R = random_orthogonal(False)
    A = RNG.normal(size=(6, 3))
    B = A @ R
    A[2] = np.nan
    assert np.allclose(procrustes_matrix(A, B), R, atol=1e-12)


# ---------------------------------------------------------------------------------- assertions
def test_assert_within_sigma_names_the_worst_numbers():
    pats = [patch(0, P_TRUE[0] + [5e-3, 0, 0]), patch(1, P_TRUE[1] + [1e-3, 0, 0])]
    c = compare(estimate(pats), truth())
    with pytest.raises(AssertionError, match=r"(?s)1 of 12 reported numbers beyond 4 sigma.*patch 0 position\.x"):
        assert_within_sigma(c, k=4)
    assert_within_sigma(c, k=6)
    assert_within_sigma(compare(estimate(pats, success=False), truth()), k=4)  # flagged: allowed
    with pytest.raises(AssertionError):
        assert_within_sigma(compare(estimate(pats, success=False), truth()), k=4, include_flagged=True)


def test_coverage_interval_is_the_central_binomial_region():
    from scipy.stats import binom

    n, p, alpha = 200, nominal_coverage(1.0), 1e-3
    lo, hi = coverage_interval(n, p, alpha)
    assert binom.cdf(lo - 1, n, p) <= alpha / 2 < binom.cdf(lo, n, p)
    assert binom.sf(hi, n, p) <= alpha / 2 < binom.sf(hi - 1, n, p)
    assert nominal_coverage(1.0) == pytest.approx(0.682689492, abs=1e-9)
    assert nominal_coverage(2.0) == pytest.approx(0.954499736, abs=1e-9)


def test_coverage_false_alarm_rate_is_at_most_alpha():
    """Honest Gaussian errors fail the coverage test at most alpha of the time."""
    alpha, n, trials = 0.05, 40, 4000
    z = np.abs(np.random.default_rng(7).normal(size=(trials, n)))
    fails = 0
    for row in z:
        try:
            assert_coverage(row, k=1.0, alpha=alpha)
        except AssertionError:
            fails += 1
    assert fails / trials <= alpha
    assert fails / trials > alpha / 10          # and the test is not vacuous


def test_coverage_catches_error_bars_too_small_by_two():
    z = np.abs(np.random.default_rng(3).normal(size=500)) * 2.0
    with pytest.raises(AssertionError, match=r"within 1 sigma.*accepted"):
        assert_coverage(z, k=1.0)
    out = assert_coverage(np.abs(np.random.default_rng(3).normal(size=500)), k=2.0)
    assert out["interval"][0] <= out["inside"] <= out["interval"][1]
    with pytest.raises(AssertionError, match="required 60.0-75.0"):
        assert_coverage(z, k=1.0, bounds=(0.60, 0.75))
    # error bars too large pass one-sided
    assert_coverage(np.abs(np.random.default_rng(3).normal(size=500)) * 0.5, k=1.0, side="under")
