"""One study cell: factors reach simulate / the sensor / the estimator as stated, the effects
switches change what they should (and nothing else), the hard-case scenes have the property
they are named for, and the measures mean what they say."""
from __future__ import annotations

import math

import numpy as np
import pytest

from stircasadi.problem import load_problem
from stircasadi.studies import PeakMemory, hard_verdict, run_cell
from stircasadi.studies.adapter import estimator_settings
from stircasadi.studies.cell import _apply_grid, _apply_sensor, build_setup
from stircasadi.studies.effects import force, stir_change
from stircasadi.studies.hardcases import HARD_CASES, build_hard_case
from stircasadi.transport import needed_bounces, simulate


def test_bin_factors_keep_the_window_and_change_the_bins():
    grid = load_problem("three_patch").build_grid()          # 0 .. 5.12 m, 5 mm bins
    g = _apply_grid(grid, {"bin_scale": 0.5})
    assert g.bin_width == pytest.approx(0.0025) and g.n_bins == 2048 and g.end == pytest.approx(grid.end)
    g = _apply_grid(grid, {"bin_width": 0.007})
    assert g.n_bins == math.ceil(5.12 / 0.007) and g.start == 0.0
    assert _apply_grid(grid, {"n_bins": 100}).n_bins == 100


def test_sensor_factors():
    from stircasadi.irf import GaussianIRF, IdealIRF
    from stircasadi.sensor import GaussianNoise, PoissonNoise

    s = load_problem("three_patch").build_sensor()
    assert isinstance(_apply_sensor(s, {"irf": "ideal"}).irf, IdealIRF)
    assert _apply_sensor(s, {"irf": 100.0}).irf == GaussianIRF.from_ps(100.0)
    assert _apply_sensor(s, {"noise": 1e-3}).noise == GaussianNoise(relative=1e-3)
    assert _apply_sensor(s, {"noise": 0.0}).noise is None
    assert _apply_sensor(s, {"noise_model": "none"}).noise is None
    assert _apply_sensor(s, {"noise_model": "poisson", "photons": 1e3}).noise == PoissonNoise(1e3)
    assert _apply_sensor(s, {"calibrated_camera": True}).calibrated_camera
    assert _apply_sensor(s, {}) is s


def test_snr_db_sets_sigma_from_the_ideal_peak():
    rec = run_cell({"problem": "three_patch", "seed": 0, "snr_db": 20.0, "estimate": False})
    mod = load_problem("three_patch")
    tr = simulate(mod.build_scene(), mod.build_grid(), sensor=mod.build_sensor())
    assert rec["measures"]["noise_sigma"] == pytest.approx(np.max(tr.stir) / 10.0, rel=1e-12)
    assert rec["measures"]["hard_verdict"] == "NOT-ESTIMATED"


def test_drop_direct_removes_one_trace_and_unknown_ids_are_refused():
    from stircasadi.studies.cell import _drop_direct

    mod = load_problem("three_patch")
    tr = simulate(mod.build_scene(), mod.build_grid(), sensor=mod.build_sensor())
    out = _drop_direct(tr, [1])
    assert not out.stir[1, 1].any() and np.array_equal(out.stir[0], tr.stir[0]) and tr.stir[1, 1].any()
    rec = run_cell({"problem": "three_patch", "seed": 0, "drop_direct": [7]})
    assert rec["status"] == "failed" and "not both illuminated and observed" in rec["error"]["message"]


def test_solver_factors_map_onto_the_estimator_settings():
    assert estimator_settings({"problem": "x"}) is None
    s = estimator_settings({"solver": "ipopt-gauss-newton", "tol": 1e-6, "max_iter": 50})
    assert (s.solver, s.ipopt.hessian, s.ipopt.tol, s.ipopt.max_iter) == ("ipopt", "gauss-newton", 1e-6, 50)
    s = estimator_settings({"solver": "ipopt-lbfgs"})
    assert s.ipopt.hessian == "limited-memory"
    s = estimator_settings({"solver": "lm-fd", "tol": 1e-9, "model_bounces": 3})
    assert (s.solver, s.lm.jacobian, s.lm.xtol, s.lm.gtol, s.bounces) == ("lm", "fd", 1e-9, 1e-9, 3)
    assert s.time_limit is None
    assert estimator_settings({"time_limit": 120}).time_limit == 120.0
    assert estimator_settings({"time_limit": 0}).time_limit is None   # 0: no limit


def test_effect_switches_change_what_they_promise():
    mod = load_problem("three_patch")
    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    ref = simulate(scene, grid, sensor=sensor)
    # a far occluder casts rays but blocks nothing: the same STIR, to the last bit
    sc, se, kw, _ = force(scene, sensor, "occlusion", "on")
    tr = simulate(sc, grid, sensor=se, **kw)
    assert tr.metadata["occlusion"] == "ray-cast (trimesh)" and ref.metadata["occlusion"].startswith("none")
    assert stir_change(ref, tr)[0] == 0.0
    # Phong with a 1e-12 lobe: glossy nodes, the same light to ~1e-12
    sc, se, kw, _ = force(scene, sensor, "glossy", "on")
    tr = simulate(sc, grid, sensor=se, **kw)
    assert tr.metadata["glossy_terms"] and not ref.metadata["glossy_terms"]
    assert stir_change(ref, tr)[0] <= 1e-9 * np.max(ref.stir)
    # one bounce more than needed adds light, but little; the ideal IRF changes the shape a lot
    sc, se, kw, _ = force(scene, sensor, "bounces", "on")
    assert kw == {"bounces": needed_bounces(scene) + 1, "allow_truncation": True}
    extra = stir_change(ref, simulate(sc, grid, sensor=se, **kw))[0] / np.max(ref.stir)
    assert 0 < extra < 1e-3
    sc, se, kw, _ = force(scene, sensor, "irf", "off")
    assert stir_change(ref, simulate(sc, grid, sensor=se, **kw))[0] / np.max(ref.stir) > 0.5
    # the automatic choice is the scene as it is
    assert force(scene, sensor, "irf", "auto")[:3] == (scene, sensor, {})


def test_removing_occluders_is_compared_on_the_shared_ids():
    rec = run_cell({"problem": "three_planes_occluded", "seed": 0, "effect": "occlusion",
                    "effect_state": "off", "estimate": False})
    m = rec["measures"]
    assert rec["status"] == "ok" and "observed 98 -> 147" in m["effect_note"]
    assert m["stir_change_rel"] > 0 and m["sim_s_auto"] > 0


def test_hard_cases_have_the_property_they_are_named_for():
    sc, _, _ = build_hard_case("equal_paths_visible")
    assert np.ptp(sc.source_distances) < 1e-12
    assert np.ptp(sc.distances[np.triu_indices(3, 1)]) < 1e-12
    sc, _, _ = build_hard_case("grazing")
    to_cam = -sc.positions[2] / np.linalg.norm(sc.positions[2])
    assert math.degrees(math.acos(sc.normals[2] @ to_cam)) == pytest.approx(85.0)
    assert sc.patch_visibility[2].any()
    sc, _, _ = build_hard_case("albedo_0999")
    assert np.all(sc.albedos == 0.999)
    sc, _, _ = build_hard_case("hidden_near_wall")
    assert sc.positions[2, 2] - sc.positions[0, 2] == pytest.approx(0.001) and sc.hidden[2]
    sc, grid, sensor = build_hard_case("dynamic_range")
    tr = simulate(sc, grid, sensor=sensor, per_bounce=True)
    ratio = np.max(tr.per_bounce[2]) / np.max(tr.per_bounce[0])
    assert 3e-7 < ratio < 3e-6
    for name in HARD_CASES:                                  # every case simulates on its grid
        s, g, se = build_hard_case(name)
        simulate(s, g, sensor=se)


def test_generator_functions_and_objects(monkeypatch):
    import sys
    import types

    from stircasadi.errors import StudyError

    mod = types.ModuleType("my_scenes")

    def tuple_gen(n_patches=3, seed=0):
        m = load_problem("three_patch")
        return m.build_scene(), m.build_grid(), m.build_sensor()

    class Generated:
        def __init__(self, seed):
            m = load_problem("three_patch")
            self.scene, self.grid, self.sensor = m.build_scene(), m.build_grid(), m.build_sensor()
            self.params = {"seed_seen": seed, "planes": 1}

    mod.tuple_gen = tuple_gen
    mod.object_gen = lambda seed, **kw: Generated(seed)
    monkeypatch.setitem(sys.modules, "my_scenes", mod)
    assert build_setup({"scene": "my_scenes:tuple_gen", "patches": 3, "seed": 4})[3] == {}
    assert build_setup({"scene": "my_scenes:object_gen", "seed": 4})[3] == {"seed_seen": 4, "planes": 1}
    rec = run_cell({"scene": "my_scenes:object_gen", "seed": 9, "estimate": False})
    assert rec["measures"]["gen_seed_seen"] == 9
    with pytest.raises(StudyError, match="does not take"):
        build_setup({"scene": "my_scenes:tuple_gen", "scene_args": {"colour": 1}, "seed": 0})
    with pytest.raises(StudyError, match="cannot be imported"):
        build_setup({"scene": "no_such_module_xyz:f", "seed": 0})


def test_peak_memory_sees_a_large_allocation():
    with PeakMemory(interval=0.002) as mem:
        a = np.ones(25_000_000)        # 200 MB, touched
        a += 1.0
        import time

        time.sleep(0.3)                # many sampling intervals, even on a loaded machine
        del a
    assert mem.delta_mb > 150


def test_hard_verdict_rules():
    base = {"success": True, "n_nonfinite": 0, "n_beyond_4sigma_unflagged": 0, "n_missed": 0}
    assert hard_verdict("ok", base) == "OK"
    assert hard_verdict("ok", {**base, "n_beyond_4sigma_unflagged": 1}) == "SILENT-WRONG"
    assert hard_verdict("ok", {**base, "success": False, "n_beyond_4sigma_unflagged": 3}) == "FLAGGED"
    assert hard_verdict("ok", {**base, "n_nonfinite": 1, "success": False}) == "NON-FINITE"
    assert hard_verdict("ok", {**base, "n_missed": 1}) == "MISSED"
    assert hard_verdict("refused", {}) == "REFUSED" and hard_verdict("crashed", {}) == "CRASHED"


def test_a_twin_cell_measures_what_compare_measures():
    """The cell's numbers are compare() of the blind estimate against the capture's truth."""
    import dataclasses

    from stircasadi.pipeline import estimate_capture
    from stircasadi.testing import compare

    rec = run_cell({"problem": "three_patch", "seed": 3})
    mod = load_problem("three_patch")
    sensor = mod.build_sensor()
    cap = sensor.capture(simulate(mod.build_scene(), mod.build_grid(), sensor=sensor), seed=3)
    comp = compare(estimate_capture(dataclasses.replace(cap, truth=None)), cap)
    assert rec["status"] == "ok"
    assert [r["err"] for r in rec["numbers"]] == [r["err"] for r in comp.rows]
    s = comp.summary()
    assert rec["numbers"], "the estimate reported no number to compare"
    for k in ("n_z", "max_abs_z", "err_position_m", "err_albedo", "n_missed", "n_null"):
        assert rec["measures"][k] == s[k] or (s[k] != s[k] and rec["measures"][k] != rec["measures"][k])
    assert rec["measures"]["n_hidden_true"] == 0 and rec["measures"]["sim_bounces"] == "2"


def test_settings_honoured_is_read_from_the_stages():
    from stircasadi.studies.adapter import _honoured

    ipopt = [{"solver": "ipopt", "iterations": 3}]
    assert _honoured({"solver": "lm-ad"}, ipopt) is False
    assert _honoured({"solver": "ipopt-gauss-newton"}, ipopt) is None          # Hessian not told
    assert _honoured({"solver": "ipopt-gauss-newton"}, [{"solver": "ipopt", "hessian": "gauss-newton"}])
    assert _honoured({"solver": "ipopt-lbfgs"}, [{"solver": "ipopt", "hessian": "exact"}]) is False
    assert _honoured({"solver": "lm-fd"}, [{"solver": "lm", "jacobian": "fd"}])
    assert _honoured({}, ipopt) is None
