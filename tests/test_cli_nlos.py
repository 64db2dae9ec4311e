"""``stircasadi estimate --method lct|fk|bp|surface --nlos KEY=VALUE`` on a relay-wall capture
file: the options reach the reconstruction (the surface fit's grid, levels and prior are the ones
asked for), and a malformed, unknown or misplaced option stops the command with exit status 2,
one clear line naming what is allowed, and nothing written."""
from __future__ import annotations

import json
import math
import os

import pytest

from nlos_twins import confocal_capture, render, surface_patches
from stircasadi.cli import main


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """The tilted-plane confocal twin (8 x 8 wall points, 1 % noise) written as a capture file."""
    hid, _ = surface_patches(lambda x, y: 0.35 + math.tan(math.radians(15.0)) * x, 0.12, 25, rho=0.7)
    stir, grid, xyz = render(8, 0.3, hid, n_bins=100, bin_width=0.01, fwhm=0.03)
    path = tmp_path_factory.mktemp("scan") / "tilted.h5"
    confocal_capture(stir, grid, xyz, noise_rel=0.01, fwhm=0.03).write(path)
    return path


def run_cli(argv, capsys):
    code = main([str(a) for a in argv])
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err + cap.out
    return code, cap.out, cap.err


def test_nlos_options_reach_the_surface_fit(scan, tmp_path, capsys):
    out = tmp_path / "e.json"
    code, _, err = run_cli(["-q", "estimate", scan, "--out", out, "--method", "surface",
                            "--nlos", "gate_m=0.2", "--nlos", "n_nodes=6", "--nlos", "levels=2",
                            "--nlos", "max_iter=4", "--nlos", "sigma0=0.01", "--nlos", "prior=gcv",
                            "--nlos", "extent=-0.15,0.15,-0.15,0.15"], capsys)
    assert code in (0, 3), err
    d = json.loads(out.read_text())
    s = d["surface"]
    assert len(s["grid"]["x"]) == 6 and len(s["levels"]) == 2
    assert s["prior_method"] == "generalised cross-validation"
    assert s["grid"]["x"][0] == pytest.approx(-0.15) and s["grid"]["x"][-1] == pytest.approx(0.15)
    assert all(so["iterations"] <= 4 for lv in s["levels"] for so in lv["solves"])


@pytest.mark.parametrize("extra, words", [
    (["--method", "surface", "--nlos", "n_nodes"], ["--nlos takes KEY=VALUE", "'n_nodes'"]),
    (["--method", "surface", "--nlos", "bogus=1"], ["Unknown option(s) ['bogus']", "n_nodes"]),
    (["--method", "surface", "--nlos", "prior=often"], ["prior must be 'auto', 'gcv', 'none'"]),
    (["--method", "surface", "--nlos", "prior=auto", "--nlos", "albedo_prior=much"],
     ["SurfaceSettings.albedo_prior must be a number or None (null)", "'much'"]),
    (["--method", "surface", "--nlos", "prior=auto", "--nlos", "albedo_prior=-1"],
     ["albedo_prior must be a finite weight >= 0, or None (null) for the default"]),
    # a value of the wrong kind, named with what the field takes (was an internal error)
    (["--method", "surface", "--nlos", "n_nodes=abc"], ["SurfaceSettings.n_nodes must be a whole number", "'abc'"]),
    (["--method", "surface", "--nlos", "sigma0=wide"], ["SurfaceSettings.sigma0 must be a number or None (null)"]),
    (["--method", "lct", "--nlos", "diffuse=maybe"], ["VolumeSettings.diffuse must be true or false", "'maybe'"]),
    (["--nlos", "n_nodes=6"], ["--nlos is for --method lct|fk|bp|surface"]),
])
def test_bad_nlos_options_are_refused(scan, tmp_path, capsys, extra, words):
    code, _, err = run_cli(["-q", "estimate", scan, "--out", tmp_path / "e.json", *extra], capsys)
    assert code == 2, err
    for w in words:
        assert w in err, (w, err)
    assert sorted(os.listdir(tmp_path)) == []


def test_settings_refuse_values_of_the_wrong_kind_and_take_numpy_scalars():
    """``check_field_types``: each field takes what its annotation names (an integral float for a
    whole number, NumPy scalars and arrays too) and refuses the rest with the field's name."""
    import numpy as np

    from stircasadi.errors import ReconstructionError
    from stircasadi.nlos import VolumeSettings
    from stircasadi.nlos.surface import SurfaceSettings

    ok = SurfaceSettings(n_nodes=np.int64(8), levels=2.0, extent=np.array([-1, 1, -1, 1.0]), edge_extent=1,
                         prior=np.float64(3.0), threads=None).validate()
    assert ok.n_nodes == 8
    VolumeSettings(z_range=[0.1, 1.0], diffuse=np.bool_(False), snr=np.float32(0.5)).validate()
    for kw, words in [({"n_nodes": 8.5}, "SurfaceSettings.n_nodes must be a whole number; got 8.5"),
                      ({"margin": True}, "SurfaceSettings.margin must be a number; got True"),
                      ({"split_steps": 2}, "SurfaceSettings.split_steps must be true or false; got 2"),
                      ({"extent": "wide"}, "SurfaceSettings.extent must be a list or None (null)")]:
        with pytest.raises(ReconstructionError) as e:
            SurfaceSettings(**kw).validate()
        assert words in str(e.value)
    with pytest.raises(ReconstructionError, match="VolumeSettings.n_depth must be a whole number or None"):
        VolumeSettings(n_depth="many").validate()


def test_library_refuses_nlos_options_outside_the_relay_wall_methods():
    """``pipeline.estimate_capture(nlos_options=...)`` on a full STIR (three_patch): refused for
    the joint fit (a relay-wall method is needed) and for method='surface' on a full STIR (that
    route has its own settings), before any fit runs."""
    from stircasadi.errors import ModelError
    from stircasadi.pipeline import estimate_capture
    from stircasadi.problems import three_patch as P
    from stircasadi.transport import simulate

    sen = P.build_sensor()
    cap = sen.capture(simulate(P.build_scene(), P.build_grid(), sensor=sen), seed=0)
    with pytest.raises(ModelError, match="nlos_options are for method 'lct' / 'fk' / 'bp' / 'surface'"):
        estimate_capture(cap, method="joint", nlos_options={"n_nodes": 6})
    with pytest.raises(ModelError, match="nlos_options are for relay-wall scans"):
        estimate_capture(cap, method="surface", nlos_options={"n_nodes": 6})
