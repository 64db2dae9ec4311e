"""The application commands end to end: results equal the library's, bad input gets one clear
line and exit status 2, nothing is overwritten that was an input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stircasadi.apps.records import read_result
from stircasadi.apps.relight import Illumination, relight_capture
from stircasadi.apps.twin import estimate_from_scene
from stircasadi.capture import Capture
from stircasadi.cli import build_parser, main
from stircasadi.problems import lambertian_walls

STD = {"position": 0.002, "normal": 0.01, "area": 1e-5, "albedo": 0.01}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("apps")
    cap = d / "cap.h5"
    assert main(["simulate", "three_patch", "--out", str(cap), "--noise", "none"]) == 0
    est = d / "est.json"
    est.write_text(json.dumps(estimate_from_scene(lambertian_walls.build_scene(), STD,
                                                  rng=np.random.default_rng(0))))
    return d, cap, est


def test_every_option_has_help():
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    for name in ("relight", "separate", "segment", "replace", "deconvolve"):
        for act in sub.choices[name]._actions:
            assert act.help, (name, act.dest)


def test_relight_by_superposition_writes_the_library_result(files):
    d, cap, _ = files
    out = d / "relit.h5"
    assert main(["relight", str(cap), "--out", str(out), "--weights", "1,0,2", "--delays", "0,0,0.05"]) == 0
    r = read_result(out)
    ref = relight_capture(Capture.read(cap), Illumination([1, 0, 2], delays=[0, 0, 0.05]))
    np.testing.assert_array_equal(r["transient"], ref.transient)
    assert (d / "relit_pictures" / "relit_steady.png").stat().st_size > 1000


def test_relight_from_the_estimate_at_a_new_viewpoint(files):
    d, _, est = files
    out = d / "novel.h5"
    assert main(["relight", "--estimate", str(est), "--out", str(out), "--camera", "0.2,0.1,0",
                 "--ids", "0,3", "--weights", "1,2", "--bin-width", "0.01"]) == 0
    r = read_result(out)
    assert r["summary"]["route"] == "estimate" and r["summary"]["camera"] == [0.2, 0.1, 0.0]
    assert r["transient_std"].shape == r["transient"].shape and np.all(r["relit_steady_std"] > 0)
    assert (d / "novel_pictures" / "relit_image.png").exists()


def test_separate_segment_replace(files):
    d, cap, est = files
    assert main(["separate", str(cap), "--out", str(d / "sep.h5"), "--nayar"]) == 0
    s = read_result(d / "sep.h5")
    np.testing.assert_allclose(s["direct"] + s["global"], Capture.read(cap).stir.sum(axis=(0, 2)), rtol=1e-12)
    assert main(["segment", str(est), "--out", str(d / "seg.json")]) == 0
    seg = json.loads((d / "seg.json").read_text())
    assert seg["format"] == "stircasadi.segmentation" and len(seg["ids"]) == 10
    assert main(["replace", str(est), "--out", str(d / "rep.h5"), "--material", "0",
                 "--segmentation", str(d / "seg.json"), "--brdf", "lambertian", "--albedo", "0.05",
                 "--no-std", "--no-pictures"]) == 0
    rep = read_result(d / "rep.h5")
    assert rep["steady_after"].sum() < rep["steady_before"].sum()
    assert not (d / "rep_pictures").exists()


def test_deconvolve_twin_and_records_file(files):
    d, _, _ = files
    rec, out = d / "rec.h5", d / "dec.h5"
    assert main(["deconvolve", "--emulate", "three_patch", "--code", "mls:11", "--noise", "1e-3",
                 "--out", str(out), "--save-records", str(rec)]) == 0
    summ = json.loads(out.with_suffix(".json").read_text())
    assert 0.3 < summ["measured_error_rms_per_bin_median"] / summ["error_rms_per_bin_median"] < 3
    out2 = d / "dec2.h5"
    assert main(["deconvolve", str(rec), "--out", str(out2), "--no-pictures"]) == 0
    np.testing.assert_allclose(Capture.read(out2).stir, Capture.read(out).stir, rtol=0, atol=0)


@pytest.mark.parametrize("argv, words", [
    (["relight", "{cap}", "--out", "{d}/x.h5", "--weights", "1,1,1,1"], "4 weights but the STIR has 3"),
    (["relight", "{cap}", "--out", "{d}/x.h5", "--ids", "0,9", "--weights", "1,1"], "Unknown illuminated patch id(s) [9]"),
    (["relight", "{cap}", "--out", "{cap}"], "is the input file"),
    (["relight", "{cap}", "--out", "{d}/x.h5", "--camera", "1,2"], "--camera must be three numbers"),
    (["relight", "{cap}", "--out", "{d}/x.h5", "--camera", "0,0,1"], "needs --estimate"),
    (["relight", "--estimate", "{est}", "--out", "{d}/x.h5", "--ids", "0,77"], "Unknown illuminated patch id(s) [77]"),
    (["replace", "{est}", "--out", "{d}/x.h5", "--ids", "1", "--brdf", "phong", "--albedo", "0.7",
      "--specular", "0.5", "--exponent", "10"], "creates energy"),
    (["replace", "{est}", "--out", "{d}/x.h5", "--ids", "1,42", "--brdf", "lambertian", "--albedo", "0.5"],
     "Unknown patch id(s) [42]"),
    (["segment", "{est}", "--out", "{est}"], "is the input file"),
    (["segment", "{d}/missing.json", "--out", "{d}/s.json"], "Estimate file not found"),
    (["separate", "{cap}", "--out", "{d}/nofolder/s.h5"], "does not exist"),
    (["deconvolve", "--emulate", "three_patch", "--code", "pulse:31", "--out", "{d}/x.h5"], "ill-conditioned"),
    (["deconvolve", "--emulate", "three_patch", "--code", "mls:7", "--out", "{d}/x.h5"], "shorter than the response"),
    (["deconvolve", "--emulate", "three_patch", "--code", "zzz", "--out", "{d}/x.h5"], "--code must be"),
])
def test_bad_input_gets_one_clear_line(files, capsys, argv, words):
    d, cap, est = files
    before = cap.read_bytes(), est.read_bytes()
    argv = [a.format(cap=cap, est=est, d=d) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert words in err and "Traceback" not in err and err.startswith(f"stircasadi {argv[0]}:")
    assert (cap.read_bytes(), est.read_bytes()) == before
