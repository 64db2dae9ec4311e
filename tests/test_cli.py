"""The command line end to end: simulate, estimate, run, plot, problems."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stircasadi.capture import Capture
from stircasadi.cli import main
from stircasadi.problem import list_problems

PNG = b"\x89PNG\r\n\x1a\n"


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
    a, b, c = tmp_path / "a.h5", tmp_path / "b.h5", tmp_path / "c.h5"
    for path, seed in ((a, 5), (b, 5), (c, 6)):
        assert main(["-q", "simulate", "three_patch", "--out", str(path), "--seed", str(seed)]) == 0
    np.testing.assert_array_equal(Capture.read(a).stir, Capture.read(b).stir)
    assert not np.array_equal(Capture.read(a).stir, Capture.read(c).stir)


def test_quiet_prints_results_only(tmp_path, capsys):
    assert main(["-q", "simulate", "three_patch", "--out", str(tmp_path / "x.h5")]) == 0
    out, err = capsys.readouterr()
    assert err == "" and "wrote" in out
    assert main(["simulate", "three_patch", "--out", str(tmp_path / "y.h5"), "-v"]) == 0
    assert "simulating 'three_patch'" in capsys.readouterr().err


def test_problems_lists_one_described_line_each(capsys):
    assert main(["problems"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    names = list_problems()
    assert len(lines) == len(names) + 1
    for name, line in zip(names, lines):
        assert line.startswith(name) and len(line.split(None, 1)[1]) > 20
    assert sum("[default]" in line for line in lines) == 1


def test_estimate_prints_table_and_summary_and_writes_schema_v2(tmp_path, capsys):
    cap = tmp_path / "three.h5"
    assert main(["-q", "simulate", "three_patch", "--out", str(cap)]) == 0
    capsys.readouterr()
    out = tmp_path / "three.json"
    assert main(["-q", "estimate", str(cap), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    d = json.loads(out.read_text())
    assert d["format"] == "stircasadi.estimate" and d["version"] == 2 and d["verdict"] == "OK"
    assert "position (m)" in text and "σ mm" in text and "err/σ" in text
    assert f"found: {len(d['patches'])} visible and 0 hidden patches" in text
    assert "checks against the data:" in text and text.rstrip().splitlines()[-2] == "verdict: OK"
    rows = [ln for ln in text.splitlines() if ln[:1].isdigit()]
    assert len(rows) == len(d["patches"])


def test_estimate_unreliable_exits_3_and_still_writes(tmp_path, capsys, monkeypatch):
    """The exit status follows the verdict; an UNRELIABLE estimate is written with its reasons."""
    from stircasadi import pipeline

    cap = tmp_path / "three.h5"
    assert main(["-q", "simulate", "three_patch", "--out", str(cap)]) == 0
    real = pipeline.estimate_capture

    def failing_checks(*a, **k):
        res = real(*a, **k)
        res.json.update(success=False, verdict="UNRELIABLE", reasons=["chi2: whitened chi2/dof 40 > 3"])
        return res
    monkeypatch.setattr(pipeline, "estimate_capture", failing_checks)
    out = tmp_path / "e.json"
    assert main(["-q", "estimate", str(cap), "--out", str(out)]) == 3
    text = capsys.readouterr().out
    assert "verdict: UNRELIABLE — chi2: whitened chi2/dof 40 > 3" in text
    assert json.loads(out.read_text())["verdict"] == "UNRELIABLE"


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    """``stircasadi run`` on the default problem, once for the tests below."""
    import contextlib
    import io

    folder = tmp_path_factory.mktemp("run")
    so, se = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
        code = main(["run", "--out", str(folder)])
    return folder, code, so.getvalue(), se.getvalue()


@pytest.mark.slow
def test_run_default_problem_prints_one_table_and_writes_every_file(default_run):
    folder, code, out, err = default_run
    assert code == 0, err
    assert "Traceback" not in out + err
    files = ["capture.h5", "estimate.json", "report.json", "scene.png", "profiles.png"]
    assert sorted(p.name for p in folder.iterdir()) == sorted(files)
    # one table, the scene's own names, units in the header
    assert out.count("position (m)") == 1 and "albedo·area (cm²)" in out
    rows = {ln.split()[1]: ln for ln in out.splitlines() if ln[:1].isdigit() and len(ln.split()) > 5}
    assert set(rows) == {"V1", "V2", "H1", "H2"}
    d = json.loads((folder / "estimate.json").read_text())
    h1 = next(p for p in d["patches"] if not p["visible"] and p["position"][0] < -0.3)
    assert f"{h1['position'][0]:.4f}" in rows["H1"]       # the row shows the estimate.json number
    # timings once, every stage and the pictures; the closing line lists every file
    assert out.count("timings (s):") == 1
    timing = next(ln for ln in out.splitlines() if ln.startswith("timings (s):"))
    for stage in ("simulate", "estimate", "joint", "pictures", "scene", "profiles", "total"):
        assert stage in timing
    wrote = out.strip().splitlines()[-1]
    assert wrote.startswith("wrote") and all(f in wrote for f in files)
    # report.json: run metadata, timings, files, truth comparison; nothing of estimate.json
    report = json.loads((folder / "report.json").read_text())
    assert report["problem"] == "hidden_corner" and report["simulation"]["bounces"] == 3
    assert set(report["files"].values()) == set(files)
    assert not ({"patches", "checks", "covariance", "distances", "stages"} & set(report))
    assert report["timings_s"]["pictures"]["total"] > 0
    assert report["truth_comparison"]["fraction_within_2_sigma"] >= 0.75
    for pic in ("scene.png", "profiles.png"):
        data = (folder / pic).read_bytes()
        assert data.startswith(PNG) and len(data) > 20_000


@pytest.mark.slow
def test_plot_a_capture_an_estimate_and_both(default_run, tmp_path, capsys):
    folder = default_run[0]
    cap, est = folder / "capture.h5", folder / "estimate.json"
    for args, pics in (([cap], {"profiles.png", "scene.png"}),      # the capture's truth: scene.png
                       ([est], {"scene.png"}),
                       ([cap, est], {"profiles.png", "scene.png"})):
        out = tmp_path / str(len(args)) / args[0].suffix[1:]
        assert main(["plot", *map(str, args), "--out", str(out), "--renderer", "matplotlib"]) == 0
        assert {p.name for p in out.iterdir()} == pics
        assert all((out / p).read_bytes().startswith(PNG) for p in pics)
    text = capsys.readouterr().out
    assert "drawn with matplotlib" in text
    assert main(["plot", str(cap), str(cap), "--out", str(tmp_path)]) == 2
    assert "two capture files" in capsys.readouterr().err


def test_run_survives_failing_pictures(tmp_path, capsys, monkeypatch):
    """A picture that fails costs neither a result file nor the other picture."""
    def broken(*a, **k):
        raise RuntimeError("no OpenGL context")
    monkeypatch.setattr("stircasadi.viz.render_scene_png", broken)
    assert main(["-q", "run", "three_patch", "--out", str(tmp_path)]) == 0
    out, err = capsys.readouterr()
    assert "scene.png skipped: RuntimeError: no OpenGL context" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capture.h5", "estimate.json", "profiles.png",
                                                           "report.json"]
    report = json.loads((tmp_path / "report.json").read_text())
    assert "scene" not in report["files"] and "no OpenGL" in report["pictures"]["scene.png"]


def test_python_dash_m_runs_the_command_line():
    r = subprocess.run([sys.executable, "-m", "stircasadi.cli", "--version"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.startswith("stircasadi ")


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


PROBLEM_FILES = sorted(p for p in (Path(__file__).resolve().parents[1] / "stircasadi" / "problems").glob("*.py")
                       if not p.name.startswith("_"))


@pytest.mark.parametrize("src", PROBLEM_FILES, ids=lambda p: p.stem)
def test_a_copied_problem_file_simulates_from_an_empty_folder(src, tmp_path):
    """Every problem file, copied alone into an empty folder outside the repository, runs by
    path (absolute imports: nothing relative to the package's folder), in a fresh process whose
    working directory is that folder; the capture equals the one the problem's name gives."""
    script = tmp_path / f"my_{src.stem}.py"
    shutil.copy(src, script)
    assert sorted(p.name for p in tmp_path.iterdir()) == [script.name]
    by_path, by_name = tmp_path / "by_path.h5", tmp_path / "by_name.h5"
    for target, out in ((str(script), by_path), (src.stem, by_name)):
        r = subprocess.run([sys.executable, "-m", "stircasadi.cli", "-q", "simulate", target, "--out", str(out),
                            "--seed", "3"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
    a, b = Capture.read(by_path), Capture.read(by_name)
    assert a.stir.shape == b.stir.shape and np.array_equal(a.stir, b.stir)


def test_a_copied_problem_file_runs_from_an_empty_folder(tmp_path):
    """``stircasadi run COPY.py`` (the route a user's own scene takes) estimates and writes its
    files from an empty folder outside the repository."""
    from stircasadi.problems import three_patch

    script = tmp_path / "my_scene.py"
    shutil.copy(three_patch.__file__, script)
    r = subprocess.run([sys.executable, "-m", "stircasadi.cli", "-q", "run", str(script), "--out", str(tmp_path / "out")],
                       cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr[-2000:]
    d = json.loads((tmp_path / "out" / "estimate.json").read_text())
    assert d["verdict"] == "OK" and len(d["patches"]) == 3
