"""The command line end to end on small problems."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stircasadi.capture import Capture
from stircasadi.cli import main


def test_simulate_writes_a_valid_noise_free_capture(tmp_path):
    out = tmp_path / "three.h5"
    assert main(["simulate", "three_patch", "--out", str(out), "--noise", "none"]) == 0
    cap = Capture.read(out)
    from stircasadi.problems import three_patch
    from stircasadi.transport import simulate
    ref = simulate(three_patch.build_scene(), three_patch.build_grid(), three_patch.build_sensor())
    np.testing.assert_array_equal(cap.stir, ref.stir)
    assert cap.truth["positions"].shape == (3, 3) and cap.noise["model"] == "none"
    assert cap.irf is not None and np.argmax(cap.irf) == len(cap.irf) // 2


def test_simulate_seeded_noise_is_reproducible(tmp_path):
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    main(["simulate", "three_patch", "--out", str(a), "--seed", "5"])
    main(["simulate", "three_patch", "--out", str(b), "--seed", "5"])
    np.testing.assert_array_equal(Capture.read(a).stir, Capture.read(b).stir)


def test_unknown_problem_and_bad_capture_give_clear_errors(tmp_path, capsys):
    assert main(["simulate", "no_such_problem", "--out", str(tmp_path / "x.h5")]) == 2
    assert "known problems" in capsys.readouterr().err
    bad = tmp_path / "bad.h5"
    bad.write_text("garbage")
    assert main(["estimate", str(bad), "--out", str(tmp_path / "e.json")]) == 2
    assert "HDF5" in capsys.readouterr().err


@pytest.mark.slow
def test_run_default_problem_writes_report_and_pictures(tmp_path):
    code = main(["run", "--out", str(tmp_path)])
    assert code == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["problem"] == "hidden_corner"
    assert report["simulation"]["bounces"] == 3
    for pic in report["pictures"]:
        assert (tmp_path / pic.split("/")[-1]).stat().st_size > 10_000


def test_import_then_estimate_real_confocal_scan(tmp_path, shared_data):
    """Stanford 40 cm resolution chart: import, estimate (geometry only: a paired capture)."""
    src = shared_data / "otoole2018_confocal" / "data_resolution_chart_40cm.mat"
    if not src.exists():
        pytest.skip(f"real data not present: {src}")
    cap_path, est_path = tmp_path / "chart.h5", tmp_path / "chart.json"
    assert main(["import", str(src), "--out", str(cap_path)]) == 0
    assert main(["estimate", str(cap_path), "--out", str(est_path)]) == 0
    d = json.loads(est_path.read_text())
    assert d["stages"]["joint"]["status"].startswith("skipped")
    hidden = [p for p in d["patches"] if not p["visible"]]
    assert hidden, "no hidden point found"
    assert abs(hidden[-1]["position"][2] - 0.40) < 0.005   # the chart stands 40 cm from the wall
