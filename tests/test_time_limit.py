"""The estimate's time limit (``stircasadi.joint.budget``): a limit that is not reached changes
nothing; one that cuts a stage never yields a result called a success; one that leaves no fit
converged is a clear refusal.

Known answers: the default problem (two visible patches, two hidden) estimated with no limit and
with a generous one gives the same numbers to the last digit; with a limit shorter than its
hidden-patch search the result is the visible patches' fit (no hidden patch), flagged by the
``time-limit`` check, whose visible numbers equal those of a run with the search switched off.
"""
from __future__ import annotations

import copy
import subprocess
import sys
import time

import numpy as np
import pytest

from stircasadi.errors import SolverError
from stircasadi.joint.budget import WALL_TIME_STATUS, Budget
from stircasadi.joint.settings import EstimateSettings
from stircasadi.pipeline import estimate_capture


@pytest.fixture(scope="module")
def capture():
    from stircasadi.cli.commands import simulate_problem

    cap = simulate_problem("hidden_corner", seed=0)[3]   # with the problem's priors (flatland)
    cap.truth = None
    return cap


def _values(d, visible_only=False):
    ps = [p for p in d["patches"] if p["visible"] or not visible_only]
    return np.concatenate([np.ravel(p["position"]) for p in ps]
                          + [np.ravel(p["normal"]) for p in ps if p.get("normal") is not None])


def test_budget_arithmetic():
    b = Budget(None)
    assert not b.limited and b.remaining() == np.inf and not b.expired() and b.ipopt_options() == {}
    b = Budget(10.0, start=time.perf_counter() - 4.0)
    assert 5.9 < b.remaining() <= 6.0 and not b.expired()
    assert 5.9 < b.ipopt_options()["max_wall_time"] <= 6.0
    b = Budget(1.0, start=time.perf_counter() - 3.0)
    assert b.expired() and b.ipopt_options()["max_wall_time"] == 1.0   # a solve may still report
    b.stop("x"), b.stop("x"), b.stop("y")
    assert b.stopped == ["x", "y"]
    for bad in (0, -1, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            Budget(bad)


def test_settings_reject_a_bad_time_limit():
    from stircasadi.errors import ModelError

    for bad in (0, -5, float("nan"), "60"):
        with pytest.raises(ModelError, match="time_limit"):
            EstimateSettings(time_limit=bad).validate()


def test_a_limit_not_reached_changes_nothing(capture):
    free = estimate_capture(capture).to_json_dict()
    lim = estimate_capture(capture, time_limit=3600.0).to_json_dict()
    assert free["success"] and lim["success"]
    assert len(lim["patches"]) == len(free["patches"]) == 4
    np.testing.assert_array_equal(_values(lim), _values(free))
    assert lim["stages"]["time_limit"]["stopped"] == []
    assert "time-limit" not in [c["name"] for c in lim["checks"]]


def test_a_limit_that_cuts_the_search_is_flagged_and_keeps_the_visible_fit(capture):
    st = EstimateSettings()
    st.search.enabled = False
    st.bounces = 2          # the order the fit starts at (the limit stops the probe of the next)
    visible = estimate_capture(capture, settings=st).to_json_dict()
    # the geometry stage and the visible fit converge even past the limit (a solve gets >= 1 s),
    # then nothing else starts
    cut = estimate_capture(capture, time_limit=1e-3).to_json_dict()
    assert cut["success"] is False and cut["verdict"] == "UNRELIABLE"
    failed = {c["name"]: c for c in cut["checks"] if not c["passed"]}
    assert "time-limit" in failed and "hidden-patch search" in failed["time-limit"]["message"]
    assert cut["stages"]["time_limit"]["stopped"] == ["bounce-order probe", "hidden-patch search"]
    assert all(p["visible"] for p in cut["patches"])       # no unrefined hidden patch reported
    np.testing.assert_allclose(_values(cut, True), _values(visible, True), rtol=0, atol=1e-12)


def test_no_fit_converged_in_time_is_a_refusal(capture):
    from stircasadi.geometry import estimate_geometry
    from stircasadi.joint.fit import fit_joint
    from stircasadi.joint.policy import VisibleStart
    from stircasadi.view import CaptureView

    view = CaptureView.of(capture, {})
    geo = estimate_geometry(capture)
    M = len(view.ids)
    X = np.asarray(geo.positions[:M])
    n = (view.camera - X) / np.linalg.norm(view.camera - X, axis=1, keepdims=True)
    start = VisibleStart(X, np.asarray(geo.position_std[:M]), n)
    st = copy.deepcopy(EstimateSettings())
    st.ipopt.tol = 1e-30            # cannot converge: the solve runs until the wall time stops it
    st.ipopt.acceptable_tol = 1e-30
    st.ipopt.max_iter = 10 ** 6
    spent = Budget(2.0)
    with pytest.raises(SolverError, match="time limit of 2 s ran out") as exc:
        fit_joint(view, start, st, budget=spent)
    assert exc.value.status == WALL_TIME_STATUS
    assert spent.elapsed() < 30.0    # IPOPT stopped at its max_wall_time, not at max_iter


def test_cli_time_limit_exit_status_and_bad_values(tmp_path, capture):
    path = tmp_path / "cap.h5"
    capture.write(path)
    out = tmp_path / "e.json"
    r = subprocess.run([sys.executable, "-m", "stircasadi.cli", "estimate", str(path), "--out", str(out),
                        "--time-limit", "0.001", "-q"], capture_output=True, text=True)
    assert r.returncode == 3, r.stderr                    # EXIT_UNRELIABLE, estimate.json written
    assert out.exists() and "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "stircasadi.cli", "estimate", str(path), "--out", str(out),
                        "--time-limit", "-4"], capture_output=True, text=True)
    assert r.returncode == 2 and "--time-limit must be a number of seconds > 0" in r.stderr
    assert "Traceback" not in r.stderr
