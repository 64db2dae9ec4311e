"""Exact CasADi derivatives of the model against central finite differences; sub-bin continuity."""
from __future__ import annotations

import casadi as ca
import numpy as np

from stircasadi.problems import glossy_patch, hidden_corner
from stircasadi.model import TransientModel

from _reflectance_helpers import hidden_model


def _fd_jacobian(f, x, h):
    J = np.empty((len(np.asarray(f(x)).ravel()), len(x)))
    for j in range(len(x)):
        e = np.zeros(len(x))
        e[j] = h
        J[:, j] = (np.asarray(f(x + e)).ravel() - np.asarray(f(x - e)).ravel()) / (2 * h)
    return J


def _check(m, x, h=1e-6, tol=1e-6):
    J = np.asarray(ca.densify(ca.Function("J", [m.x], [ca.jacobian(m.y_sym, m.x)])(x)))
    Jfd = _fd_jacobian(lambda z: m.f_y(z), x, h)
    err = np.linalg.norm(J - Jfd, axis=0) / np.maximum(np.linalg.norm(J, axis=0), 1e-300)
    assert np.all(np.isfinite(J))
    assert err.max() < tol, err
    return J


def test_jacobian_hidden_plane_positions_and_albedos_matches_fd():
    sc, gr, se = hidden_corner.build_scene(), hidden_corner.build_grid(), hidden_corner.build_sensor()
    m, h = hidden_model(sc, gr, se.irf, offsets=[[0.004, -0.003], [0.002, 0.005]])
    m.setup()
    rng = np.random.default_rng(3)
    x = m.x0 + rng.uniform(-0.2, 0.2, m.n_x)
    J = _check(m, x)
    assert np.all(np.abs(J[:, -4:]).max(axis=0) > 0)  # every in-plane coordinate moves the output


def test_jacobian_extended_hidden_patch_area_and_tilts_matches_fd():
    """A hidden disc (its quadrature points move with its area and its normal)."""
    sc, gr, se = hidden_corner.build_scene(), hidden_corner.build_grid(), hidden_corner.build_sensor()
    h = np.flatnonzero(sc.hidden)
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.6)
    m.set_extended(h).set_albedo_product(h)
    m.set_unknown("area", h, lower=1e-4, upper=0.09, scale=0.01)
    m.set_unknown("tilt", h).set_unknown("tilt2", h)
    m.set_unknown("position", h, lower=-0.02, upper=0.02, scale=0.02)
    m.setup()
    _check(m, m.x0 + 0.05, h=1e-5, tol=1e-5)


def test_jacobian_hidden_positions_matches_fd():
    sc, gr, se = hidden_corner.build_scene(), hidden_corner.build_grid(), hidden_corner.build_sensor()
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.6)
    h = np.flatnonzero(sc.hidden)
    m.set_unknown("position", h, lower=-0.02, upper=0.02, scale=0.02)
    m.setup()
    # flatland scene: the out-of-plane derivatives are near zero by symmetry, so a step of 1e-6
    # is round-off limited; 1e-4 keeps the central difference's O(h^2) error below 1e-8
    _check(m, m.x0 + 0.1, h=1e-4)


def test_jacobian_phong_matches_fd_and_is_finite_outside_the_lobe():
    sc, gr, se = glossy_patch.build_scene(), glossy_patch.build_grid(), glossy_patch.build_sensor()
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.4)
    m.set_unknown("specular", "glossy", initial=0.3).set_unknown("exponent", "glossy", initial=12.0)
    m.setup()
    _check(m, m.x0, h=1e-6, tol=1e-5)


def test_delay_moves_continuously_between_bins():
    """A sub-bin change of a hidden position changes the STIR smoothly (no rounding steps)."""
    sc, gr, se = hidden_corner.build_scene(), hidden_corner.build_grid(), hidden_corner.build_sensor()
    m, h = hidden_model(sc, gr, se.irf)
    m.setup()
    w = gr.bin_width
    j = m.n_x - 1  # last in-plane coordinate
    steps = np.linspace(-0.5, 0.5, 21) * w / m.x_scale[j]
    ys = np.array([m.evaluate(m.x0 + np.eye(m.n_x)[j] * s) for s in steps])
    d = np.diff(ys, axis=0)
    # equal steps give nearly equal differences (smooth), never a jump concentrated in one step
    norms = np.linalg.norm(d, axis=1)
    assert norms.max() / norms.min() < 1.5
    assert norms.min() > 0
