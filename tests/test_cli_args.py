"""Every bad argument, input and output of the commands: exit status 2, one clear line, no
traceback, and no input or earlier output changed (driven through ``stircasadi.cli.main``)."""
from __future__ import annotations

import errno
import hashlib
import os
import shutil

import h5py
import pytest

from stircasadi.cli import build_parser, main
from stircasadi.cli.args import BOUNCES_MAX, HIDDEN_MAX, SEED_MAX
from stircasadi.problems import three_patch


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A small capture (three_patch, its sensor's noise) written by the command itself."""
    path = tmp_path_factory.mktemp("cap") / "three.h5"
    assert main(["-q", "simulate", "three_patch", "--out", str(path)]) == 0
    return path


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_cli(argv, capsys):
    code = main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err + cap.out
    return code, cap.out, cap.err


ARGUMENT_CASES = [
    (["run", "--seed", "-1"], ["--seed", f"from 0 to {SEED_MAX}", "got -1"]),
    (["run", "--seed", str(2 ** 80)], ["--seed", f"from 0 to {SEED_MAX}", str(2 ** 80)]),
    (["simulate", "three_patch", "--out", "{tmp}/x.h5", "--seed", "1.5"], ["--seed", "whole number"]),
    (["simulate", "three_patch", "--out", "{tmp}/x.h5", "--bounces", "0"],
     ["--bounces", f"from 1 to {BOUNCES_MAX}", "'all'"]),
    (["simulate", "three_patch", "--out", "{tmp}/x.h5", "--bounces", "two"], ["--bounces", "whole number"]),
    (["run", "no_such_problem", "--out", "{tmp}/run"], ["Unknown problem", "known problems", "hidden_corner"]),
    (["simulate", "{tmp}/missing.py", "--out", "{tmp}/x.h5"], ["not found", "missing.py"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--hidden", "-1"],
     ["--hidden", f"from 0 to {HIDDEN_MAX}", "omit --hidden"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--hidden", "many"], ["--hidden", "whole number"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--brdf", "ward"], ["--brdf", "invalid choice"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--areas", "{{bad"], ["--areas", "JSON object"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--areas", '{{"0": -1}}'], ["--areas", "> 0 m^2"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--maps", "{tmp}/m"], ["--maps is for --method"]),
    (["estimate", "{cap}", "--out", "{tmp}/e.json", "--method", "lct"], ["is for relay-wall scans"]),
    (["plot", "{tmp}/nothing.h5"], ["does not exist"]),
    (["run", "--renderer", "opengl"], ["--renderer", "invalid choice"]),
]


@pytest.mark.parametrize("argv, words", ARGUMENT_CASES, ids=[" ".join(a[:2] + a[-2:]) for a, _ in ARGUMENT_CASES])
def test_bad_argument_is_refused_with_the_allowed_values(argv, words, capture, tmp_path, capsys):
    code, out, err = run_cli([a.format(tmp=tmp_path, cap=capture) for a in argv], capsys)
    assert code == 2, err
    for w in words:
        assert w in err, (w, err)
    assert sorted(os.listdir(tmp_path)) == []  # nothing was written


def _truncated(src, dst):
    data = src.read_bytes()
    dst.write_bytes(data[: len(data) // 2])


def _foreign_hdf5(_, dst):
    with h5py.File(dst, "w") as f:
        f["x"] = [1, 2, 3]


@pytest.mark.parametrize("make, words", [
    (lambda src, dst: None, ["does not exist"]),
    (lambda src, dst: dst.mkdir(), ["is a folder"]),
    (lambda src, dst: dst.write_text("not a capture at all"), ["not an HDF5 file"]),
    (lambda src, dst: dst.write_text('{"format": "stircasadi.estimate"}'), ["not an HDF5 file"]),
    (_truncated, ["not a readable HDF5 file"]),
    (_foreign_hdf5, ["format"]),
], ids=["missing", "folder", "text", "json", "truncated", "foreign-hdf5"])
def test_unreadable_or_corrupt_capture_is_refused(make, words, capture, tmp_path, capsys):
    bad = tmp_path / "bad.h5"
    make(capture, bad)
    before = digest(bad) if bad.is_file() else None
    out = tmp_path / "e.json"
    code, _, err = run_cli(["estimate", bad, "--out", out], capsys)
    assert code == 2
    assert all(w in err for w in words), err
    assert str(bad) in err
    assert not out.exists()
    assert (digest(bad) if bad.is_file() else None) == before


def test_output_folder_missing_is_a_file_or_a_folder(capture, tmp_path, capsys):
    code, _, err = run_cli(["estimate", capture, "--out", tmp_path / "no" / "e.json"], capsys)
    assert code == 2 and "does not exist" in err and "mkdir -p" in err
    (tmp_path / "d.json").mkdir()
    code, _, err = run_cli(["estimate", capture, "--out", tmp_path / "d.json"], capsys)
    assert code == 2 and "is a folder" in err
    code, _, err = run_cli(["simulate", "three_patch", "--out", tmp_path / "d.json"], capsys)
    assert code == 2 and "is a folder" in err
    code, _, err = run_cli(["simulate", "three_patch", "--out", tmp_path / "x.txt"], capsys)
    assert code == 2 and ".h5" in err
    afile = tmp_path / "afile"
    afile.write_text("keep me")
    code, _, err = run_cli(["run", "--out", afile], capsys)
    assert code == 2 and "exists and is a file" in err
    code, _, err = run_cli(["plot", capture, "--out", afile], capsys)
    assert code == 2 and "exists and is a file" in err
    assert afile.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "d.json"]


def test_run_checks_every_file_of_its_folder_before_simulating(tmp_path, capsys):
    (tmp_path / "estimate.json").mkdir()  # a folder where run would write a file
    code, out, err = run_cli(["run", "three_patch", "--out", tmp_path], capsys)
    assert code == 2 and "estimate.json is a folder" in err
    assert out == "" and sorted(p.name for p in tmp_path.iterdir()) == ["estimate.json"]


def test_output_equal_to_an_input_is_refused_and_the_input_kept(capture, tmp_path, capsys):
    before = digest(capture)
    code, _, err = run_cli(["estimate", capture, "--out", capture], capsys)
    assert code == 2 and "is the input file" in err
    assert digest(capture) == before
    script = tmp_path / "my_scene.py"
    shutil.copy(three_patch.__file__, script)
    code, _, err = run_cli(["simulate", script, "--out", script], capsys)
    assert code == 2 and "is the input file" in err
    assert "build_scene" in script.read_text()
    # plot: an estimate that happens to be called scene.png, pictures into its own folder
    pic = tmp_path / "scene.png"
    pic.write_text('{"format": "stircasadi.estimate", "version": 2, "patches": []}')
    code, _, err = run_cli(["plot", pic, "--out", tmp_path], capsys)
    assert code == 2 and "is the input file" in err
    assert pic.read_text().startswith('{"format"')


def test_read_only_output_folder_is_refused(capture, tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    real = os.access
    # root ignores permission bits: emulate a read-only folder where the OS would refuse writes
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: False if os.fspath(p) == str(ro)
                        and mode & os.W_OK else real(p, mode, *a, **k))
    for argv in (["estimate", capture, "--out", ro / "e.json"], ["run", "three_patch", "--out", ro],
                 ["simulate", "three_patch", "--out", ro / "c.h5"], ["plot", capture, "--out", ro]):
        code, _, err = run_cli(argv, capsys)
        assert code == 2 and "not writable" in err, (argv, err)
    assert list(ro.iterdir()) == []


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root ignores permission bits")
def test_read_only_output_folder_really_read_only(capture, tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        code, _, err = run_cli(["estimate", capture, "--out", ro / "e.json"], capsys)
        assert code == 2 and "not writable" in err
    finally:
        ro.chmod(0o755)


def test_a_failed_write_keeps_the_previous_output(capture, tmp_path, capsys, monkeypatch):
    out = tmp_path / "e.json"
    out.write_text("previous estimate")

    def disk_full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr("stircasadi.io.os.replace", disk_full)
    code, _, err = run_cli(["estimate", capture, "--out", out], capsys)
    assert code == 2 and "No space left on device" in err and "Nothing was changed" in err
    assert out.read_text() == "previous estimate"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.json"]  # no temporary file left


def test_an_internal_error_is_one_line_and_verbose_shows_the_traceback(capture, tmp_path, capsys, monkeypatch):
    def boom(*a, **k):
        raise ZeroDivisionError("division by zero")
    monkeypatch.setattr("stircasadi.pipeline.estimate_capture", boom)
    code, _, err = run_cli(["estimate", capture, "--out", tmp_path / "e.json"], capsys)
    assert code == 1 and "internal error (ZeroDivisionError" in err and "-vv" in err
    assert main(["-vv", "estimate", str(capture), "--out", str(tmp_path / "e.json")]) == 1
    assert "Traceback" in capsys.readouterr().err
    assert not (tmp_path / "e.json").exists()


def test_every_option_has_help_and_shows_its_default():
    import argparse

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in ("run", "simulate", "estimate", "plot", "problems"):
        sp = sub.choices[name]
        text = sp.format_help()
        for a in sp._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            assert a.help, (name, a.option_strings or a.dest)
            if a.option_strings and a.default not in (None, False, argparse.SUPPRESS):
                assert f"(default: {a.default})" in " ".join(text.split()), (name, a.option_strings)


def test_help_and_version_exit_zero(capsys):
    assert main(["--version"]) == 0
    assert "stircasadi" in capsys.readouterr().out
    assert main(["estimate", "--help"]) == 0
    assert "docs/estimate-json.md" in " ".join(capsys.readouterr().out.split())
