"""The import / export / acquire commands: bad arguments and unsafe outputs get one clear line."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from stircasadi.acquisition.cli import main
from stircasadi.capture import Capture


def _run(args, capsys):
    try:
        rc = main(args)
    except SystemExit as exc:               # argparse refuses a malformed argument
        rc = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err


@pytest.mark.parametrize("args, says", [
    (["--shots", "0"], "--shots: must be an integer >= 1; got '0'"),
    (["--emulate-photons", "-5"], "--emulate-photons: must be a number > 0; got '-5'"),
    (["--emulate-fault", "explode:ACQ:2"], "--emulate-fault: must be KIND:COMMAND[:NTH] with KIND one of"),
    (["--emulate-fault", "disconnect:ACQ:x"], "--emulate-fault: must be an integer >= 1; got 'x'"),
    (["--emulate-fault", "disconnect"], "--emulate-fault: must be KIND:COMMAND[:NTH]"),
    (["--retries", "-1"], "--retries: must be an integer >= 0"),
    (["--patches", "0,a"], "--patches: must be comma-separated integers"),
])
def test_bad_acquire_arguments_are_refused_clearly(tmp_path, capsys, args, says):
    rc, err = _run(["acquire", "--emulate", "three_patch", "--out", str(tmp_path / "c.h5"), *args], capsys)
    assert rc == 2 and says in err
    assert not list(tmp_path.iterdir())


def test_acquire_output_folder_missing_refused_before_work(tmp_path, capsys):
    rc, err = _run(["acquire", "--emulate", "three_patch", "--out", str(tmp_path / "no" / "c.h5"),
                    "--quiet"], capsys)
    assert rc == 2 and "does not exist" in err and err.count("\n") == 1


def test_acquire_help_shows_defaults():
    out = subprocess.run([sys.executable, "-m", "stircasadi.acquisition.cli", "acquire", "--help"],
                         capture_output=True, text=True, timeout=60).stdout
    for text in ("--baud BAUD", "(default: 115200)", "--retries RETRIES", "(default: 2)", "(default: 1000)",
                 "--resource RESOURCE"):
        assert text in " ".join(out.split()) or text in out


def _npz(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, stir=np.ones((1, 2, 5)), start=0.0, bin_width=1.0, time_unit="ps")
    return p


def test_import_onto_its_input_is_refused(tmp_path, capsys):
    p = _npz(tmp_path)
    before = p.read_bytes()
    rc, err = _run(["import", str(p), "--out", str(p)], capsys)
    assert rc == 2 and "is the input file" in err
    assert p.read_bytes() == before


@pytest.mark.parametrize("where", ["missing", "folder"])
def test_import_to_an_unwritable_place_is_refused(tmp_path, capsys, where):
    p = _npz(tmp_path)
    out = tmp_path / "nope" / "c.h5" if where == "missing" else tmp_path
    rc, err = _run(["import", str(p), "--out", str(out)], capsys)
    assert rc == 2 and ("does not exist" in err or "is a folder" in err)


def test_import_then_export_ytal_then_import_again(tmp_path, capsys):
    p = _npz(tmp_path)
    cap_path, y = tmp_path / "c.h5", tmp_path / "c.hdf5"
    assert _run(["import", str(p), "--out", str(cap_path)], capsys)[0] == 0
    assert _run(["export", str(cap_path), "--format", "ytal", "--out", str(y)], capsys)[0] == 0
    rc, err = _run(["export", str(cap_path), "--format", "ytal", "--out", str(cap_path)], capsys)
    assert rc == 2 and "is the input file" in err
    back = tmp_path / "back.h5"
    assert _run(["import", str(y), "--out", str(back)], capsys)[0] == 0
    np.testing.assert_array_equal(Capture.read(back).stir, Capture.read(cap_path).stir)


def test_unknown_file_refused_with_the_list_of_formats(tmp_path, capsys):
    p = tmp_path / "x.bin"
    p.write_bytes(b"\0" * 10)
    rc, err = _run(["import", str(p), "--out", str(tmp_path / "c.h5")], capsys)
    assert rc == 2 and "stanford-lct, ccsocr, general-nlos, ytal, znlos, ptu, phu, csv, npz" in err
