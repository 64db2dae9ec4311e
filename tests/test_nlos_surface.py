"""Hidden-surface fit: the relay physics against the project's transport, the CasADi pair
Jacobian against finite differences, a tilted-plane twin with error bars, and the end-to-end
estimate_capture -> estimate.json / files."""
import json
import math

import numpy as np
import pytest

from nlos_twins import WALL_RHO, confocal_capture, render, surface_patches
from stircasadi.brdf import Lambertian
from stircasadi.irf import GaussianIRF
from stircasadi.nlos import VolumeSettings, estimate_capture, from_capture, lct
from stircasadi.nlos.surface import SurfaceSettings, fit_surface
from stircasadi.nlos.surface.grid import DepthGrid
from stircasadi.nlos.surface.model import SurfaceModel
from stircasadi.nlos.surface.physics import relay_amplitude, relay_delay
from stircasadi.scene import Patch, Scene
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import simulate


def test_relay_amplitude_and_delay_match_transport():
    """One hidden patch seen from two wall patches: the time-integrated third bounce of
    transport.simulate equals relay_amplitude with gain f(L) f(D), and arrives at relay_delay."""
    L, D = np.array([-0.1, 0.05, 0.0]), np.array([0.15, -0.05, 0.0])
    X = np.array([0.03, 0.02, 0.4])
    nX = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    rho, a = 0.6, 1e-3
    wall = [Patch(tuple(L), (0, 0, 1), 1e-4, Lambertian(WALL_RHO)),
            Patch(tuple(D), (0, 0, 1), 1e-4, Lambertian(WALL_RHO))]
    hid = Patch(tuple(X), tuple(nX), a, Lambertian(rho), hidden=True)
    scene = Scene(wall + [hid], source=(0.0, -0.5, 0.5))
    g = TimeGrid(0.0, 0.002, 600)
    tr = simulate(scene, g, Sensor(irf=GaussianIRF(0.01)), method="bounces", bounces=3,
                  legs_included=False, allow_truncation=True)
    y = tr.stir[0, 1]
    n = np.array([0.0, 0.0, 1.0])
    A = relay_amplitude(L, D, n, n, X, nX, a, rho, (WALL_RHO / math.pi) ** 2)
    assert y.sum() == pytest.approx(A, rel=1e-9)
    t_mean = float(np.sum(g.centres * y) / y.sum())
    assert t_mean == pytest.approx(relay_delay(L, D, X, 0.0), abs=1e-4)


def test_pair_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    frame = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))
    grid = DepthGrid(np.linspace(-0.1, 0.1, 3), np.linspace(-0.1, 0.1, 3), frame)
    from stircasadi.nlos.relay import Relay
    P = np.array([[0.05, -0.02, 0.0]])
    rl = Relay(np.zeros((1, 400)), TimeGrid(0.0, 0.003, 400), P, P, np.array([[0, 0, 1.0]]),
               np.array([[0, 0, 1.0]]), 0.0, 1.0)
    z = 0.4 + 0.01 * rng.standard_normal(grid.n)
    model = SurfaceModel(grid, rl, z, 0.01, 0.01)
    p0 = np.array([0.41, 0.1, -0.2, 0.7, 0.006])
    q = np.concatenate([grid.base_points()[4], P[0], P[0], [0, 0, 1.0], [0, 0, 1.0], [0.0, 1.0, 0.75]])
    y0, J = (np.asarray(v) for v in model.f_jac(p0, q))
    for j in range(5):
        h = 1e-6 * max(abs(p0[j]), 1e-3)
        e = np.zeros(5)
        e[j] = h
        fd = (np.asarray(model.f_val(p0 + e, q)) - np.asarray(model.f_val(p0 - e, q))) / (2 * h)
        assert np.allclose(J[:, j], fd.ravel(), rtol=1e-5, atol=1e-7 * np.abs(J).max())


@pytest.fixture(scope="module")
def tilted_plane():
    """A plane tilted 15 deg about y, 0.35 m from an 8 x 8 confocal wall scan (0.6 m), sampled
    by 25 x 25 small patches (finer than the 3 cm IRF), 1 % Gaussian noise."""
    tilt = math.radians(15.0)
    hid, truth = surface_patches(lambda x, y: 0.35 + math.tan(tilt) * x, 0.12, 25, rho=0.7)
    stir, grid, xyz = render(8, 0.3, hid, n_bins=100, bin_width=0.01, fwhm=0.03)
    cap = confocal_capture(stir, grid, xyz, noise_rel=0.01, fwhm=0.03)
    truth["normal_true"] = np.array([math.sin(tilt), 0.0, -math.cos(tilt)])
    return cap, truth


def test_tilted_plane_twin_depth_normal_albedo_and_coverage(tilted_plane):
    """Measured (8 x 8 nodes, 1 level, no prior): depth MAE 0.48 mm, normal error 1.3 deg, IRF
    FWHM 30.6 mm (true 30), chi2/dof 1.43, 94 % of the nodes within 2 sigma of the truth."""
    cap, truth = tilted_plane
    rl = from_capture(cap)
    rl.gain[:] = (WALL_RHO / math.pi) ** 2            # an absolute relay: known wall albedo
    maps = lct(rl, VolumeSettings(gate_m=0.2)).maps()
    res = fit_surface(rl, maps, SurfaceSettings(n_nodes=8, levels=1, known_gain=True,
                                                sigma0=0.01, max_iter=20), gate=0.2)
    tg = DepthGrid(truth["x"], truth["y"], res.grid.frame)
    inside = (np.abs(res.grid.x)[None, :] < 0.1) & (np.abs(res.grid.y)[:, None] < 0.1)
    sel = res.mask & inside
    assert sel.sum() >= 10
    zt = tg.resample(truth["depth"], res.grid).reshape(res.shape)
    err = np.abs(res.depth - zt)[sel]
    assert err.mean() < 0.002
    ang = np.degrees(np.arccos(np.clip(res.normals[sel] @ truth["normal_true"], -1, 1)))
    assert ang.mean() < 4.0
    assert abs(np.median(res.albedo[sel]) - 0.7) < 0.15
    assert abs(res.fwhm_irf - 0.03) < 0.1 * 0.03
    cover = np.mean(err / res.depth_std[sel] < 2.0)
    assert cover >= 0.9
    assert np.all(res.depth_std[sel] > 0) and res.chi2_dof < 2


def test_estimate_capture_json_and_files(tilted_plane, tmp_path):
    cap, _ = tilted_plane
    est = estimate_capture(cap, method="lct", gate_m=0.2, out_dir=tmp_path / "lct")
    d = json.loads((tmp_path / "lct" / "estimate.json").read_text())
    assert d["format"] == "stircasadi.estimate" and d["version"] == 2
    assert len(d["patches"]) == int(est.maps.mask.sum()) and not d["patches"][0]["visible"]
    assert d["patches"][0]["albedo_std"] is None and "albedo_std" in d["patches"][0]["notes"]
    ids = {p["id"] for p in d["patches"]}
    assert min(ids) > int(cap.obs_ids().max())
    for f in ("maps.npz", "surface.ply", "maps.png", "view3d.png"):
        assert (tmp_path / "lct" / f).stat().st_size > 0
    est = estimate_capture(cap, method="surface", gate_m=0.2, n_nodes=6, levels=1, max_iter=8,
                           sigma0=0.01, out_dir=tmp_path / "surf")
    d = json.loads((tmp_path / "surf" / "estimate.json").read_text())
    assert len(d["patches"]) == 36 and d["surface"]["files"]["mesh"] == "surface.ply"
    p = d["patches"][0]
    assert len(p["position_std"]) == 3 and p["albedo_std"] is not None
    assert d["verdict"] in ("OK", "UNRELIABLE") and (d["verdict"] == "OK") == d["success"]
    assert {c["name"] for c in d["checks"]} == {"solver", "chi2"}
    from stircasadi.errors import ReconstructionError
    with pytest.raises(ReconstructionError, match="method"):
        estimate_capture(cap, method="nope")
    with pytest.raises(ReconstructionError, match="Unknown option"):
        estimate_capture(cap, method="lct", bogus=1)
