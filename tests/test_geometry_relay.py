"""Real relay-wall data: importers and the hidden-object depth of the Stanford 40 cm charts."""

import numpy as np
import pytest
import scipy.io as sio

from stircasadi.acquisition import importers as nm
from stircasadi.constants import C
from stircasadi.datasets import data_dir
from stircasadi.errors import ImportFormatError
from stircasadi.geometry import estimate_geometry
from stircasadi.geometry import relay

DATA = data_dir()
STANFORD = DATA / "otoole2018_confocal"


@pytest.mark.parametrize("name", ["data_resolution_chart_40cm.mat", "data_dot_chart_40cm.mat"])
def test_stanford_40cm_chart_depth_within_5mm(name):
    f = STANFORD / name
    if not f.exists():
        pytest.skip(f"data file absent: {f}")
    cap = nm.read_stanford_lct(f)
    assert cap.traces.shape == (4096, 2048) and not cap.legs_included
    assert np.isclose(cap.grid.bin_width, 4e-12 * C)
    est = estimate_geometry(cap)
    depth = est.extras["depth_m"]
    assert abs(depth - 0.40) < 0.005, depth
    assert est.stats["hidden_point"].success


def test_confocal_twin_experiment_point_and_plane():
    """Simulated confocal scan of a plane at 0.5 m: onsets -> plane depth and point."""
    from stircasadi.capture import Capture
    from stircasadi.timegrid import TimeGrid

    rng = np.random.default_rng(0)
    n = 16
    lin = np.linspace(-0.3, 0.3, n)
    yy, xx = np.meshgrid(lin, lin, indexing="ij")
    P = np.stack([xx.ravel(), yy.ravel(), np.zeros(n * n)], axis=1)
    grid = TimeGrid(0.0, 0.002, 1024)
    c = (np.arange(1024) + 0.5) * 0.002
    from scipy.special import ndtr
    t0 = 2 * 0.5  # plane z = 0.5 parallel to the wall: earliest return 2 * 0.5
    lam = 50 * ndtr((c - t0) / 0.006) * np.exp(-np.clip(c - t0, 0, None) / 0.3) + 0.5
    tr = rng.poisson(np.tile(lam, (n * n, 1))).astype(float)
    ids = np.arange(n * n)
    cap = Capture(grid=grid, traces=tr, pairs=np.stack([ids, ids], 1), legs_included=False,
                  illuminated_xyz=P, observed_xyz=P, illuminated_ids=ids, observed_ids=ids,
                  noise={"model": "poisson"})
    est = relay.estimate_relay(cap, gate_m=0.2)
    assert abs(est.extras["plane_depth_m"] - 0.5) < 0.003
    # a compact target: onsets on spheres around X -> the point fit recovers X
    X = np.array([0.05, -0.02, 0.45])
    t = 2 * np.linalg.norm(P - X, axis=1)
    lam = 50 * ndtr((c[None] - t[:, None]) / 0.006) * np.exp(-np.clip(c[None] - t[:, None], 0, None) / 0.05) + 0.5
    cap = Capture(grid=grid, traces=rng.poisson(lam).astype(float), pairs=np.stack([ids, ids], 1),
                  legs_included=False, illuminated_xyz=P, observed_xyz=P, illuminated_ids=ids,
                  observed_ids=ids, noise={"model": "poisson"})
    est = relay.estimate_relay(cap, gate_m=0.2)
    assert np.linalg.norm(est.positions[1] - X) < 0.005


def test_importers_on_real_files_and_errors(tmp_path):
    statue = DATA / "fk2019_statue_confocal"
    tuan = DATA / "generalnlos2024_tuan"
    if statue.exists():
        cap = nm.read_ccsocr(statue)
        assert cap.traces.shape == (4096, 512) and np.isclose(cap.grid.bin_width, 32e-12 * C)
        assert np.allclose(np.ptp(cap.illuminated_xyz[:, :2], axis=0), 2.0)
        assert nm.sniff(statue) == "ccsocr"
    if tuan.exists():
        cap = nm.read_general_nlos(tuan)
        assert cap.traces.shape[0] == 4096 and cap.observed_xyz.shape == (4096, 3)
        # after rectification the wall return sits ~14.5 bins before t = 0 (NOTES.md)
        s = cap.traces.sum(0)
        k = int(np.argmax(s[:100]))
        assert -20 < (cap.grid.start / cap.grid.bin_width + k) < -10
        assert nm.sniff(tuan) == "general-nlos"
    bad = tmp_path / "bad.mat"
    sio.savemat(bad, {"rect_data": np.zeros((4, 4, 8))})
    with pytest.raises(ImportFormatError, match="width"):
        nm.read_stanford_lct(bad)
    sio.savemat(bad, {"something": np.zeros(3)})
    with pytest.raises(ImportFormatError, match="rect_data"):
        nm.read_stanford_lct(bad)
    assert nm.sniff(bad) is None


# Documented figures (data NOTES.md, half path = depth-like distance from the wall, metres):
# summed-histogram 20 % onset and peak of the hidden return.
STATUE_DOC = {"onset": 0.95, "peak": 1.11, "domain": (0.9, 1.3)}   # f-k statue, CC-SOCR domain
TUAN_DOC = {"onset": 0.72, "peak": 0.80}                            # general-NLOS "tuan"


def _relay_summary(cap):
    est = estimate_geometry(cap)
    on = est.extras["onsets"]
    half = on["tau"][on["used"]] / 2
    # tolerance on a half-path figure: one bin of quantisation of the documented bin index plus
    # one IRF FWHM (a 20 % threshold crossing of the summed histogram and the fitted 50 % edge of
    # one trace differ by a fraction of the blur), halved from path to depth
    tol = (cap.grid.bin_width + on["fwhm"]) / 2
    q = {p: float(np.percentile(half, p)) for p in (2, 20, 50)}
    return est, half, q, tol


def test_fk_statue_onsets_between_documented_onset_and_peak():
    """Measured: per-trace onsets (half path) p2/p20/p50 = 0.965/0.997/1.045 m; plane depth 1.052 m,
    point depth 0.971 m; tol = 12 mm. Documented: onset 0.95, peak 1.11, domain 0.9-1.3 m. The
    per-trace p20 sits 4.7 cm after the documented onset because the estimator uses the strongest
    25 % of traces, the documented onset is of the sum of all 4096."""
    d = DATA / "fk2019_statue_confocal"
    if not (d / "sub_Sig.mat").exists():
        pytest.skip(f"data absent: {d}")
    est, half, q, tol = _relay_summary(nm.read_ccsocr(d))
    assert np.isfinite(est.positions).all() and est.stats["hidden_plane"].success
    assert half.size > 500
    lo, hi = STATUE_DOC["onset"] - tol, STATUE_DOC["peak"] + tol
    for p, v in q.items():
        assert lo <= v <= hi, (p, v, lo, hi)
    for v in (est.extras["plane_depth_m"], est.extras["depth_m"]):
        assert lo <= v <= hi, (v, lo, hi)
        assert STATUE_DOC["domain"][0] <= v <= STATUE_DOC["domain"][1]


def test_general_nlos_tuan_onset_matches_documented():
    """Paired non-confocal scan (L-D 0.25-0.29 m apart). Measured: per-trace onsets (half path)
    p2/p20/p50 = 0.697/0.723/0.764 m; tol = 12 mm. Documented: onset 0.72 (20 % of the summed
    histogram: compared with the 20th percentile of per-trace onsets), peak 0.80 m."""
    d = DATA / "generalnlos2024_tuan"
    if not (d / "data_tuan.mat").exists():
        pytest.skip(f"data absent: {d}")
    cap = nm.read_general_nlos(d)
    est, half, q, tol = _relay_summary(cap)
    assert np.isfinite(est.positions).all() and half.size > 500
    assert abs(q[20] - TUAN_DOC["onset"]) <= tol, (q[20], tol)
    assert TUAN_DOC["onset"] - tol <= q[50] <= TUAN_DOC["peak"] + tol, q[50]
    # the single-point fit lies in front of the earliest surface (an extended object's onsets
    # put one best point nearer the wall), and within the authors' volume z in [0, 2] m
    assert 0.0 < est.extras["depth_m"] <= q[20]
