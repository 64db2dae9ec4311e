"""Pictures: traces chosen from the data, the model and whitened residuals drawn as computed,
the scene drawn with the *estimated* normals and sizes in the truth's frame, and a matplotlib
fallback whenever pyvista is missing or fails."""
from __future__ import annotations

import sys

import matplotlib
import numpy as np
import pytest

from stircasadi.capture import Capture
from stircasadi.irf import GaussianIRF, sampled
from stircasadi.timegrid import TimeGrid
from stircasadi.viz import (informative_traces, profiles_figure, render_scene_png, save_figure,
                            scene_drawing, scene_figure)

PNG = b"\x89PNG\r\n\x1a\n"
W = 0.005          # bin width, m
SIGMA = 1e-4       # noise std


def _pulse(grid, t0, amp, irf):
    h = sampled(irf, grid.bin_width)
    y = np.zeros(grid.n_bins)
    k = int(round((t0 - grid.start) / grid.bin_width - 0.5))
    y[k - len(h) // 2:k + len(h) // 2 + 1] += amp * h / h.max()
    return y


@pytest.fixture(scope="module")
def synthetic():
    """3 x 3 STIR built by hand: which trace holds which return is known.

    (0, 1) has no second bounce (patches that do not face); (0, 2) the strongest second bounce,
    (1, 2) a weaker one; (1, 1) and (2, 2) first bounces with later (third-bounce) returns of
    amplitude 100 and 30 noise std."""
    grid = TimeGrid(0.0, W, 800)
    irf = GaussianIRF.from_ps(210.0)
    rng = np.random.default_rng(3)
    clean = np.zeros((3, 3, grid.n_bins))
    for i, t in enumerate((2.0, 2.1, 2.2)):
        clean[i, i] += _pulse(grid, t, 1.0, irf)
    clean[0, 2] += _pulse(grid, 2.5, 200 * SIGMA, irf)
    clean[2, 0] += _pulse(grid, 2.5, 200 * SIGMA, irf)
    clean[1, 2] += _pulse(grid, 2.6, 40 * SIGMA, irf)
    clean[2, 1] += _pulse(grid, 2.6, 40 * SIGMA, irf)
    clean[1, 1] += _pulse(grid, 3.0, 100 * SIGMA, irf)
    clean[2, 2] += _pulse(grid, 3.3, 30 * SIGMA, irf)
    stir = clean + rng.normal(0, SIGMA, clean.shape)
    cap = Capture(grid, stir=stir, irf=sampled(irf, W), noise={"model": "gaussian", "sigma": SIGMA})
    return cap, clean


def test_informative_traces_are_chosen_from_the_data(synthetic):
    cap, _ = synthetic
    sel, sig = informative_traces(cap, n_second=2, n_later=2)
    assert abs(sig / SIGMA - 1) < 0.1                       # noise from the data alone
    second = [(t.ill, t.obs) for t in sel if t.why == "second bounce"]
    later = [(t.ill, t.obs) for t in sel if t.why == "later return"]
    # the strongest first, one of each reciprocal pair, never the pair without a second bounce
    assert [frozenset(p) for p in second] == [frozenset({0, 2}), frozenset({1, 2})]
    assert later == [(1, 1), (2, 2)]
    t11 = next(t for t in sel if (t.ill, t.obs) == (1, 1))
    assert abs(t11.times[t11.family] - 3.0) <= W and abs(t11.times[0] - 2.1) <= W


def test_profiles_draw_the_model_and_the_whitened_residual(synthetic):
    cap, clean = synthetic
    backend = matplotlib.get_backend()
    fig = profiles_figure(cap, model=clean, sigma=SIGMA, names={0: "A", 1: "B", 2: "C"})
    assert matplotlib.get_backend() == backend      # nothing switched the session's backend
    sel, _ = informative_traces(cap, SIGMA)
    main_axes = [ax for ax in fig.axes if ax.get_title(loc="left")]
    resid_axes = [ax for ax in fig.axes if ax.get_ylabel() == "resid./σ"]
    assert len(main_axes) == len(resid_axes) == len(sel) == 4
    Y = cap.stir.reshape(-1, cap.grid.n_bins)
    M = clean.reshape(-1, cap.grid.n_bins)
    for tr, ax, ar in zip(sel, main_axes, resid_axes):
        assert f"pulse at {'ABC'[tr.ill]}, seen at {'ABC'[tr.obs]}" in ax.get_title(loc="left")
        data, model = ax.get_lines()[0], ax.get_lines()[1]
        t = data.get_xdata()
        win = np.isin(np.round(cap.grid.centres, 9), np.round(t, 9))
        np.testing.assert_allclose(model.get_ydata(), M[tr.row][win])
        np.testing.assert_allclose(ar.get_lines()[0].get_ydata(), (Y[tr.row][win] - M[tr.row][win]) / SIGMA)
        assert ax.get_yscale() == "symlog"


def test_profiles_without_a_model_and_on_paired_traces(synthetic, tmp_path):
    cap, _ = synthetic
    pairs = np.array([(0, 0), (0, 2), (1, 1)])
    paired = Capture(cap.grid, traces=np.stack([cap.stir[i, j] for i, j in pairs]), pairs=pairs, irf=cap.irf)
    fig = profiles_figure(paired)
    assert not [ax for ax in fig.axes if ax.get_ylabel() == "resid./σ"]
    assert save_figure(fig, tmp_path / "p.png").read_bytes().startswith(PNG)
    with pytest.raises(ValueError, match="the model has"):
        profiles_figure(cap, model=np.zeros((2, 3, cap.grid.n_bins)))


def _plane_normal(square):
    n = np.cross(square[1] - square[0], square[3] - square[0])
    return n / np.linalg.norm(n)


def _truth():
    return {"positions": np.array([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [0.1, 0.2, 0.5]]),
            "normals": np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]),
            "areas": np.array([0.01, 0.01, 0.04]), "visible": np.array([True, True, False])}


def _estimate(truth, R=np.eye(3), frame="capture"):
    n0 = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])   # not the true normal
    P, N = truth["positions"] @ R.T, np.vstack([n0, truth["normals"][1:]]) @ R.T
    pats = [{"id": 0, "name": "V0", "visible": True, "position": P[0].tolist(), "normal": N[0].tolist(),
             "area": 4e-4},
            {"id": 1, "name": "V1", "visible": True, "position": P[1].tolist(), "normal": N[1].tolist(),
             "area": None, "unidentifiable": ["area"], "notes": {"area": "not identified"}},
            {"id": 7, "name": "H7", "visible": False, "position": P[2].tolist(), "normal": N[2].tolist(),
             "area": None, "extent": 0.05}]
    return {"format": "stircasadi.estimate", "version": 2, "frame": frame, "source_xyz": [0.0, 0.0, 0.0],
            "camera_xyz": [0.0, 0.0, 0.0], "patches": pats}, n0


def test_scene_draws_the_estimated_normals_and_sizes():
    truth = _truth()
    est, n0 = _estimate(truth)
    d = scene_drawing(est, truth, names={0: "A", 1: "B", 7: "H"})
    layers = {ly.label: ly for ly in d.layers}
    vis, hid = layers["estimate: 2 visible"], layers["estimate: 1 hidden"]
    assert len(vis.squares) == 1                      # patch 1 has no area: a marker, not a square
    np.testing.assert_allclose(np.linalg.norm(vis.squares[0][1] - vis.squares[0][0]), 0.02)
    assert abs(abs(_plane_normal(vis.squares[0]) @ n0) - 1) < 1e-12   # the estimated normal
    np.testing.assert_allclose(vis.markers, truth["positions"][[1]])
    np.testing.assert_allclose(vis.arrow_vec[0] / np.linalg.norm(vis.arrow_vec[0]), n0)
    np.testing.assert_allclose(np.linalg.norm(hid.squares[0][1] - hid.squares[0][0]), 0.05)  # extent
    tv = layers["truth: 2 visible"]
    np.testing.assert_allclose(np.linalg.norm(tv.squares[0][1] - tv.squares[0][0]), 0.1)
    assert [t for _, t, _ in d.labels] == ["A", "B", "H"]
    assert d.scale == 0.2 and np.allclose(d.source, 0)


def test_scene_moves_a_source_origin_estimate_onto_the_truth():
    truth = _truth()
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ np.diag([1, -1, 1])   # rotation and mirror
    est, n0 = _estimate(truth, R, frame="source-origin")
    d = scene_drawing(est, truth)
    vis = next(ly for ly in d.layers if ly.label.startswith("estimate: 2 visible"))
    np.testing.assert_allclose(vis.arrow_from, truth["positions"][:2], atol=1e-12)
    np.testing.assert_allclose(vis.arrow_vec[0] / np.linalg.norm(vis.arrow_vec[0]), n0, atol=1e-12)


def test_scene_picture_falls_back_to_matplotlib(tmp_path, monkeypatch):
    truth = _truth()
    est, _ = _estimate(truth)
    path, used = render_scene_png(tmp_path / "a.png", est, truth, backend="matplotlib")
    assert used == "matplotlib" and path.read_bytes().startswith(PNG)
    monkeypatch.setitem(sys.modules, "pyvista", None)             # pyvista not installed
    path, used = render_scene_png(tmp_path / "b.png", est, truth)
    assert used == "matplotlib" and path.read_bytes().startswith(PNG)
    monkeypatch.delitem(sys.modules, "pyvista")

    def broken(*a, **k):
        raise RuntimeError("no OpenGL")
    monkeypatch.setattr("stircasadi.viz.scene_vtk.render_pyvista", broken)
    path, used = render_scene_png(tmp_path / "c.png", est, truth, backend="pyvista")
    assert used == "matplotlib" and path.read_bytes().startswith(PNG)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png", "c.png"]


def test_scene_picture_with_pyvista_off_screen(tmp_path, capfd):
    pytest.importorskip("pyvista")
    from stircasadi.progress import set_verbosity

    set_verbosity(0)  # VTK's own messages are shown only with -v
    truth = _truth()
    est, _ = _estimate(truth)
    path, used = render_scene_png(tmp_path / "s.png", est, truth, title="pyvista", backend="pyvista")
    assert used == "pyvista"
    img = matplotlib.image.imread(path)
    red = (img[..., 0] > 0.8) & (img[..., 1] < 0.2) & (img[..., 2] < 0.2)
    assert red.sum() > 50 and img[..., :3].std() > 0.05      # the source drawn, not a blank frame
    assert "X server" not in capfd.readouterr().err


def test_scene_figure_is_labelled():
    truth = _truth()
    est, _ = _estimate(truth)
    fig = scene_figure(est, truth, title="t")
    ax = fig.axes[0]
    assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()) == ("x (m)", "y (m)", "z (m)")
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    for want in ("truth: 2 visible", "truth: 1 hidden", "estimate: 2 visible", "estimate: 1 hidden",
                 "source (pulsed laser)", "scale bar: 20 cm", "◆ size not identified"):
        assert want in labels, labels
