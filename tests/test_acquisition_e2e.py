"""End to end: the emulated rig (forward model of the 3-patch problem) captured through the real
drivers over pseudo-terminals; the Capture equals the forward model within the noise and the
distances come back."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from stircasadi.acquisition.calibration import first_peaks
from stircasadi.acquisition.cli import forward_source, main
from stircasadi.capture import Capture

PHOTONS, SHOTS = 2e4, 1000


@pytest.fixture(scope="module")
def forward():
    return forward_source("three_patch")


@pytest.fixture(scope="module")
def captured(tmp_path_factory, forward):
    out = tmp_path_factory.mktemp("e2e") / "three_patch.h5"
    rc = main(["acquire", "--emulate", "three_patch", "--out", str(out), "--shots", str(SHOTS),
               "--emulate-photons", str(PHOTONS), "--timeout", "0.5", "--quiet", "--seed", "1"])
    assert rc == 0
    return Capture.read(out)


def test_capture_equals_forward_model_within_noise(captured, forward):
    trace_for, n_patch, n_obs, grid, tr = forward
    ideal = np.asarray(tr.stir)
    gain = PHOTONS / (ideal.max() * SHOTS)
    expect = SHOTS * gain * ideal                      # expected counts
    assert captured.stir.shape == ideal.shape == (3, 3, grid.n_bins)
    assert captured.grid.start == pytest.approx(grid.start, abs=1e-9)
    assert captured.grid.bin_width == pytest.approx(grid.bin_width, rel=1e-7)
    z = (captured.stir - expect) / np.sqrt(expect + 1.0)
    assert np.max(np.abs(z)) < 6.5                     # Poisson, ~9000 bins
    assert abs(np.mean(z)) < 0.05
    # the total flux per trace agrees to the Poisson error
    tot, etot = captured.stir.sum(-1), expect.sum(-1)
    assert np.all(np.abs(tot - etot) <= 5 * np.sqrt(etot) + 1)
    assert captured.provenance["emulated_problem"] == "three_patch"


def test_first_bounce_paths_recover_distances(captured, forward):
    """Independent of the estimator: first-bounce peaks of stir[i, i] give |s-z_i| + |z_i-o|."""
    *_, tr = forward
    from stircasadi.problems import three_patch
    scene = three_patch.build_scene()
    pos = np.asarray(scene.positions)
    s, o = np.asarray(scene.source), np.asarray(scene.camera)
    truth = np.linalg.norm(pos - s, axis=1) + np.linalg.norm(pos - o, axis=1)
    diag = np.stack([captured.stir[i, i] for i in range(3)])
    pk = first_peaks(diag)
    measured = captured.grid.start + (pk + 0.5) * captured.grid.bin_width
    np.testing.assert_allclose(measured, truth, atol=0.25 * captured.grid.bin_width + 2e-3)


def test_stircasadi_estimate_recovers_distances(captured, tmp_path):
    cli = pytest.importorskip("stircasadi.cli", reason="stircasadi.cli (estimate) not written yet")
    if not hasattr(cli, "main"):
        pytest.skip("stircasadi.cli has no main() yet")
    cap_path = tmp_path / "cap.h5"
    captured.write(cap_path)
    out = tmp_path / "estimate.json"
    rc = subprocess.run([sys.executable, "-m", "stircasadi.cli", "estimate", str(cap_path), "--out",
                         str(out)], capture_output=True, text=True, timeout=170)
    if ("invalid choice: 'estimate'" in rc.stderr or "not available in this build" in rc.stderr
            or "No module named 'stircasadi." in rc.stderr):  # pipeline still being written
        pytest.skip("the estimate pipeline is not available yet: " + rc.stderr.strip()[-200:])
    assert rc.returncode == 0, rc.stderr[-2000:]
    import json
    est = json.loads(out.read_text())
    from stircasadi.problems import three_patch
    truth = np.asarray(three_patch.build_scene().positions)
    d_true = np.linalg.norm(truth[:, None] - truth[None], axis=-1)
    pos = np.array([p["position"] for p in est["patches"] if p["visible"]])
    d_est = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    np.testing.assert_allclose(d_est, d_true, atol=0.02)
