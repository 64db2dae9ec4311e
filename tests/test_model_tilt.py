"""Normal unknowns ("tilt", "tilt2"): the symbolic model at rotated normals equals the numeric
forward model of the rotated scene (1e-9), and its derivatives equal finite differences."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from stircasadi.brdf import Lambertian
from stircasadi.errors import ModelError
from stircasadi.model import TransientModel
from stircasadi.scene import Patch, Scene
from stircasadi.irf import GaussianIRF
from stircasadi.sensor import Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import simulate


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def flatland_corner(normals=None) -> Scene:
    """The flatland hidden corner (every patch, the source and the camera in y = 0)."""
    nr = [(0.0, 0.0, -1.0), _unit((-1.0, 0.0, -0.3)), _unit((0.3, 0.0, 1.0)), _unit((-0.2, 0.0, 1.0))]
    if normals is not None:
        nr = normals
    spec = [((-0.20, 0.0, 1.20), 0.01, 0.8, "V1"), ((0.45, 0.0, 0.90), 0.01, 0.6, "V2"),
            ((-0.45, 0.0, 0.60), 0.04, 0.7, "H1"), ((0.10, 0.0, 0.55), 0.04, 0.5, "H2")]
    return Scene([Patch(p, tuple(n), a, Lambertian(r), name=nm) for (p, a, r, nm), n in zip(spec, nr)],
                 name="flatland_corner")


GRID = TimeGrid(0.0, 0.005, 1024)
IRF = GaussianIRF(0.210 * 0.299792458)  # 210 ps FWHM in metres of path


def _model_at(sc, n0, tilt=None, tilt2=None, axis=None):
    """A model of ``sc``'s geometry but with initial normals ``n0`` (tilts free on every patch)."""
    m = TransientModel(sc.positions, n0, sc.areas, GRID, IRF, sc.illuminated_ids, sc.observed_ids,
                       sc.brdfs, source=sc.source, camera=sc.camera, phi=sc.phi,
                       visibility=sc.patch_visibility, bounces=3)
    m.set_unknown("albedo", "all", initial=0.5)
    if axis is not None:
        m.set_tilt_axes("all", axis)
    m.set_unknown("tilt", "all")
    if tilt2 is not None:
        m.set_unknown("tilt2", "all")
    return m.setup()


def _rotate(n, ax, a, b=0.0):
    u = np.cross(ax, n)
    return np.cos(b) * (np.cos(a) * n + np.sin(a) * u) + np.sin(b) * ax


def test_in_plane_tilt_reproduces_the_numeric_model():
    sc = flatland_corner()
    tr = simulate(sc, GRID, Sensor(irf=IRF))
    ax = np.array([0.0, 1.0, 0.0])
    alpha = np.radians([20.0, -35.0, 40.0, -15.0])
    n0 = np.array([_rotate(n, ax, -a) for n, a in zip(sc.normals, alpha)])  # truth = n0 rotated by alpha
    m = _model_at(sc, n0, axis=ax)
    x = m.x_of({"albedo": sc.albedos, "tilt": alpha})
    assert np.allclose(m.theta(x)["normal"], sc.normals, atol=1e-12)
    y = m.simulate(x)
    assert np.abs(y - tr.stir).max() / tr.stir.max() < 1e-9
    assert np.abs(m.simulate(m.x_of({"albedo": sc.albedos})) - tr.stir).max() / tr.stir.max() > 1e-3


def test_two_tilts_reproduce_the_numeric_model_out_of_plane():
    sc0 = flatland_corner()
    rng = np.random.default_rng(5)
    a, b = rng.uniform(-0.3, 0.3, 4), rng.uniform(-0.3, 0.3, 4)
    m0 = TransientModel.from_scene(sc0, GRID, IRF)          # default axes, perpendicular to n0
    n_true = np.array([_rotate(sc0.normals[k], m0.tilt_axis[k], a[k], b[k]) for k in range(4)])
    sc = flatland_corner(normals=n_true)
    tr = simulate(sc, GRID, Sensor(irf=IRF))
    m = _model_at(sc, sc0.normals, tilt2=True)
    th = m.theta(m.x_of({"albedo": sc.albedos, "tilt": a, "tilt2": b}))
    assert np.allclose(th["normal"], n_true, atol=1e-12)
    y = m.simulate(m.x_of({"albedo": sc.albedos, "tilt": a, "tilt2": b}))
    assert np.abs(y - tr.stir).max() / tr.stir.max() < 1e-9


def test_tilt_jacobian_matches_finite_differences():
    sc = flatland_corner()
    m = _model_at(sc, sc.normals, tilt2=True)
    x = m.x0 + np.random.default_rng(2).uniform(-0.2, 0.2, m.n_x)
    J = np.asarray(ca.densify(ca.Function("J", [m.x], [ca.jacobian(m.y_sym, m.x)])(x)))
    h = 1e-6
    Jfd = np.column_stack([(np.asarray(m.f_y(x + h * e)).ravel() - np.asarray(m.f_y(x - h * e)).ravel()) / (2 * h)
                           for e in np.eye(m.n_x)])
    err = np.linalg.norm(J - Jfd, axis=0) / np.maximum(np.linalg.norm(J, axis=0), 1e-300)
    assert np.all(np.isfinite(J)) and err.max() < 1e-6, err
    tilt_cols = [j for j, nm in enumerate(m.x_names) if nm.startswith("tilt")]
    assert np.all(np.abs(J[:, tilt_cols]).max(axis=0) > 0)  # every tilt moves the output


def test_tilt_axis_parallel_to_the_normal_is_refused():
    sc = flatland_corner()
    m = TransientModel.from_scene(sc, GRID, IRF)
    with pytest.raises(ModelError, match="perpendicular to the normal"):
        m.set_tilt_axes([0], sc.normals[0])
