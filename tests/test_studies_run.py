"""Running studies: Dask (2 loopback workers) gives the serial table; an interrupted study
resumes without recomputing finished cells; failing cells are recorded, not raised; the CLI."""
from __future__ import annotations

import json

import pandas as pd
import pytest

from stircasadi.studies import RunSettings, Study, load_results, run_study
from stircasadi.studies import runner as runner_mod
from stircasadi.studies.cache import CellCache

# engine mechanics: 4 cells that simulate only (two noise levels x two seeds; fast)
TINY = {"name": "tiny", "repetitions": 2, "seed": 5,
        "base": {"problem": "three_patch", "estimate": False},
        "cases": [{"label": "ok"}],
        "factors": {"noise": [1e-4, 1e-3]}}
# one cell that estimates, one that only simulates, and two that fail in the simulation (a
# 10-bin grid cannot hold the scene's paths)
WITH_FAILURE = {"name": "mixed", "repetitions": 1, "seed": 5, "base": {"problem": "three_patch"},
                "cases": [{"label": "ok"}, {"label": "short grid", "n_bins": 10}],
                "factors": {"noise": [1e-5, 1e-3]},
                "exclude": [{"label": "ok", "noise": 1e-3}]}
WITH_FAILURE["cases"].append({"label": "simulated", "estimate": False})
# two cells that estimate and report numbers
ESTIMATED = {"name": "estimated", "repetitions": 1, "seed": 5, "base": {"problem": "three_patch"},
             "factors": {"noise": [1e-6, 1e-5]}}

# columns that legitimately differ between two runs of the same cells
VOLATILE = ("wall_s", "simulate_s", "estimate_s", "capture_s", "sim_s_auto", "stage_time_s",
            "peak_rss_mb", "peak_rss_delta_mb", "worker")


def stable(df: pd.DataFrame) -> pd.DataFrame:
    cols = [c for c in df.columns if c not in VOLATILE]
    return df[cols].sort_values("cell").reset_index(drop=True)


@pytest.fixture
def counted(monkeypatch):
    """Count the cells this process executes (the serial runner's calls of run_cell)."""
    calls = []
    real = runner_mod.run_cell

    def wrapper(params, *a, **k):
        calls.append(params)
        return real(params, *a, **k)

    monkeypatch.setattr(runner_mod, "run_cell", wrapper)
    return calls


def test_dask_two_workers_give_the_serial_table(tmp_path):
    serial = run_study(WITH_FAILURE, tmp_path / "serial", settings=RunSettings(workers=0, figures=False))
    dask = run_study(WITH_FAILURE, tmp_path / "dask", settings=RunSettings(workers=2, figures=False))
    assert dask.provenance["run"]["mode"] == "LocalCluster(2 workers)"
    assert dask.provenance["run"]["workers"]["n"] == 2
    assert len(serial.cells) == 5
    assert (serial.cells["status"] == "ok").sum() == 3
    assert serial.cells["n_numbers"].max() > 0                         # the estimate reported
    assert set(dask.cells["worker"]) != set(serial.cells["worker"])   # it really ran elsewhere
    pd.testing.assert_frame_equal(stable(serial.cells), stable(dask.cells))
    pd.testing.assert_frame_equal(serial.numbers.sort_values(["cell", "patch_id", "quantity", "component"])
                                  .reset_index(drop=True),
                                  dask.numbers.sort_values(["cell", "patch_id", "quantity", "component"])
                                  .reset_index(drop=True))
    bad = serial.cells[serial.cells["label"] == "short grid"].iloc[0]
    assert (serial.cells["label"] == "short grid").sum() == 2
    assert bad["status"] == "failed" and bad["stage"] == "simulate" and bad["error_type"] == "TimeGridError"
    assert "n_bins" in bad["error"]


def test_cache_lists_finished_records_not_a_write_in_progress(tmp_path):
    """A record is written through a hidden temporary ``.<key>.json.*.json`` beside it; while that
    write is under way (or after a kill removed it) the cache lists only finished records."""
    from stircasadi.io import atomic_path

    cache = CellCache(tmp_path / "cells")
    cache.put("aaaa", {"status": "ok"})
    with atomic_path(cache.path("bbbb")) as tmp:
        tmp.write_text("{")                              # half a record, mid-write
        assert tmp.name.startswith(".") and tmp.suffix == ".json"
        assert len(list(cache.folder.glob("*.json"))) == 2   # what a bare glob would count
        assert cache.keys() == ["aaaa"] and not cache.done("bbbb")
    assert cache.keys() == ["aaaa", "bbbb"]
    with pytest.raises(KeyboardInterrupt), atomic_path(cache.path("cccc")) as tmp:
        tmp.write_text("{")
        raise KeyboardInterrupt                          # a kill mid-write: nothing is left behind
    assert cache.keys() == ["aaaa", "bbbb"] and len(list(cache.folder.iterdir())) == 2


def test_interrupted_study_resumes_without_recomputing(tmp_path, counted):
    out = tmp_path / "r"
    n = len(Study.from_dict(TINY).cells())

    def stop_after_two(key, rec):
        if len(counted) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(TINY, out, settings=RunSettings(workers=0, figures=False), on_result=stop_after_two)
    assert len(counted) == 2
    assert len(CellCache(out / "cells").keys()) == 2
    partial = load_results(out)                       # partial tables were written
    assert len(partial.cells) == 2 and partial.provenance["run"]["interrupted"]

    tables = run_study(TINY, out, settings=RunSettings(workers=0, figures=False, cached_only=True))
    assert len(counted) == 2 and len(tables.cells) == 2 and tables.provenance["run"]["n_missing"] == n - 2
    done_first = {json.dumps(p, sort_keys=True) for p in counted}
    res = run_study(TINY, out, settings=RunSettings(workers=0, figures=False))
    assert len(counted) == n                          # only the n - 2 others ran
    assert not done_first & {json.dumps(p, sort_keys=True) for p in counted[2:]}
    assert res.provenance["run"]["n_cached"] == 2 and res.provenance["run"]["n_computed"] == n - 2
    assert len(res.cells) == n and (res.cells["status"] == "ok").all()

    run_study(TINY, out, settings=RunSettings(workers=0, figures=False))
    assert len(counted) == n                          # a rerun of a finished study runs nothing

    full = run_study(TINY, tmp_path / "full", settings=RunSettings(workers=0, figures=False))
    pd.testing.assert_frame_equal(stable(res.cells), stable(full.cells))


def test_retry_failed_and_fresh(tmp_path, counted):
    out = tmp_path / "f"
    run_study(WITH_FAILURE, out, settings=RunSettings(workers=0, figures=False))
    assert len(counted) == 5
    run_study(WITH_FAILURE, out, settings=RunSettings(workers=0, figures=False, retry_failed=True))
    assert len(counted) == 7 and {c["label"] for c in counted[5:]} == {"short grid"}
    run_study(WITH_FAILURE, out, settings=RunSettings(workers=0, figures=False, fresh=True))
    assert len(counted) == 12


def test_dask_interrupt_closes_the_cluster_and_keeps_finished_cells(tmp_path, counted):
    import psutil

    out = tmp_path / "d"
    seen = []

    def stop_first(key, rec):
        seen.append(key)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(TINY, out, settings=RunSettings(workers=2, figures=False), on_result=stop_first)
    assert len(seen) == 1 and (out / "cells" / f"{seen[0]}.json").is_file()
    left = [c for c in psutil.Process().children(recursive=True) if c.is_running()
            and c.status() != psutil.STATUS_ZOMBIE
            and "resource_tracker" not in " ".join(c.cmdline())]   # multiprocessing's own helper
    assert not left
    res = run_study(TINY, out, settings=RunSettings(workers=0, figures=False))
    assert len(res.cells) == 4 and (res.cells["status"] == "ok").all()
    # the cell finished before the interruption is not recomputed (others may have been cached too)
    assert seen[0] not in {json.dumps(p, sort_keys=True) for p in counted}
    assert len(counted) == 4 - res.provenance["run"]["n_cached"] and len(counted) <= 3


def test_estimator_refusals_and_crashes_are_recorded(tmp_path, monkeypatch):
    from stircasadi.errors import GeometryError
    from stircasadi.studies import adapter, run_cell

    def refuse(capture, params):
        raise GeometryError("no onsets")

    monkeypatch.setattr(adapter, "run_estimate", refuse)
    rec = run_cell({"problem": "three_patch", "seed": 0})
    assert rec["status"] == "refused" and rec["stage"] == "estimate"
    assert rec["error"]["type"] == "GeometryError" and rec["measures"]["hard_verdict"] == "REFUSED"

    def crash(capture, params):
        return [][1]

    monkeypatch.setattr(adapter, "run_estimate", crash)
    rec = run_cell({"problem": "three_patch", "seed": 0})
    assert rec["status"] == "crashed" and "IndexError" in rec["error"]["traceback"]


def test_the_estimator_never_sees_the_truth(monkeypatch):
    from stircasadi.studies import adapter, run_cell

    seen = {}
    real = adapter.run_estimate

    def spy(capture, params):
        seen["truth"] = capture.truth
        return real(capture, params)

    monkeypatch.setattr(adapter, "run_estimate", spy)
    rec = run_cell({"problem": "three_patch", "seed": 0})
    assert seen["truth"] is None and rec["status"] == "ok" and rec["numbers"]


def test_tables_and_provenance_round_trip(tmp_path):
    res = run_study(ESTIMATED, tmp_path / "p", size=None, settings=RunSettings(workers=0))
    back = load_results(tmp_path / "p")
    pd.testing.assert_frame_equal(res.cells, back.cells)
    p = back.provenance
    assert p["version"] and p["seeds"] == [5] and p["machine"]["node"] and p["run"]["mode"] == "serial"
    assert (tmp_path / "p" / "summary.md").read_text().startswith("# estimated")
    names = {f.name for f in back.figures}
    assert {"accuracy_vs_noise.png", "coverage.png"} <= names
    # every estimated cell's numbers are in the numbers table, tied by cell key
    reported = back.cells[(back.cells["status"] == "ok") & (back.cells["n_numbers"] > 0)]
    assert len(reported) and set(back.numbers["cell"]) == set(reported["cell"])
    counts = back.numbers.groupby("cell").size()
    assert all(counts[c] == n for c, n in zip(reported["cell"], reported["n_numbers"]))


def test_cli_runs_a_spec_file_and_reports_failures(tmp_path, capsys):
    from stircasadi.cli import main

    spec = tmp_path / "s.toml"
    spec.write_text('name = "cli"\n[base]\nproblem = "three_patch"\n[[cases]]\nlabel = "ok"\n'
                    '[[cases]]\nlabel = "short"\nn_bins = 10\n')
    assert main(["study", str(spec), "--out", str(tmp_path / "o"), "--serial", "-q", "--no-figures"]) == 1
    err = capsys.readouterr().err
    assert "1 cell(s) failed" in err
    assert main(["study", "--report", str(tmp_path / "o")]) == 0
    assert main(["study", "--list"]) == 0
    assert "accuracy-vs-time" in capsys.readouterr().out
    assert main(["study", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not found" in err[0]
    assert main(["study", "three_patch_typo", "--out", str(tmp_path / "x")]) == 2
    (tmp_path / "afile").write_text("")
    assert main(["study", str(spec), "--out", str(tmp_path / "afile"), "--serial", "-q"]) == 2


def test_sigterm_stops_the_cli_and_keeps_finished_cells(tmp_path):
    """A killed study (SIGTERM) exits 130 with its finished cells cached; rerun resumes."""
    import signal
    import subprocess
    import sys
    import time

    spec = tmp_path / "s.toml"
    spec.write_text('name = "term"\nrepetitions = 40\n[base]\nproblem = "three_planes"\nestimate = false\n')
    out = tmp_path / "o"
    exe = [sys.executable, "-m", "stircasadi.cli", "study", str(spec), "--out", str(out), "--serial", "-q"]
    proc = subprocess.Popen(exe, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 600  # a loaded machine can take minutes for the first cell
    def finished():   # records only: a record being written is a hidden temporary .json beside it
        return len(CellCache(out / "cells").keys()) if (out / "cells").is_dir() else 0

    while time.monotonic() < deadline and finished() < 1:
        time.sleep(0.05)
    assert proc.poll() is None, "the study ended before the first cell was cached"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    n_done = finished()
    assert proc.returncode == 130 and "interrupted" in err
    assert 1 <= n_done < 40
    assert load_results(out).provenance["run"]["interrupted"]
