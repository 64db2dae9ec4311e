"""Third-bounce relay transport of one hidden surface element: amplitude, delay and bin deposit.

When to use: the analysis-by-synthesis surface fit (``stircasadi.nlos.surface``) evaluates this
on NumPy arrays (the forward model) and on CasADi symbols (its exact derivatives): one formula,
two backends (STYLE.md rule 13). It calls the project's ``radiometry.form_factor`` and
``irf.bin_integral``; the small backend-generic cosine and distance helpers written here are
what ``radiometry.cosines`` (NumPy only) lacks.

Equation (DESIGN.md section 3 conventions; light of energy phi aimed at relay point L, the
camera reading the radiance of relay point D). A hidden element X (normal nX, area a, albedo
rho, Lambertian) adds to trace p the amplitude

    A = phi g_p (rho / pi) F(1, cos_L, cos_XL, |X - L|) F(a, cos_XD, cos_D, |X - D|)

where F(a, c1, c2, d) = a max(c1, 0) max(c2, 0) / d^2 is ``radiometry.form_factor`` (the area
of L cancels against the irradiance phi / a_L) and g_p = f(L) f(D) the relay BRDFs. It
arrives at

    tau = leg_p + |X - L| + |X - D|

and bin [t_k, t_k + w) receives A * B(t_k - tau, w) through the impulse response's bin
integral B (``irf.bin_integral``; a GaussianIRF of std sigma keeps tau differentiable).

Neglects: occlusion between hidden elements and of relay legs, hidden-to-hidden interreflection
(fourth and higher bounces), the variation of distances and cosines across an element.
"""
from __future__ import annotations

import math

import numpy as np

from ... import _backend as B
from ...irf import GaussianIRF, bin_integral
from ...radiometry import form_factor

__all__ = ["dot3", "norm3", "relay_amplitude", "relay_delay", "deposit_window", "cell_spread"]


def dot3(a, b):
    """Dot product of 3-vectors: NumPy arrays (..., 3) or CasADi column vectors (3, 1)."""
    if B.is_symbolic(a, b):
        import casadi as ca
        return ca.dot(a, b)
    return np.sum(np.asarray(a) * np.asarray(b), axis=-1)


def norm3(a):
    """Euclidean norm of 3-vectors (NumPy (..., 3) or CasADi (3, 1))."""
    return B.sqrt(dot3(a, a))


def relay_delay(L, D, X, leg):
    """Path length leg + |X - L| + |X - D| (metres)."""
    return leg + norm3(X - L) + norm3(X - D)


def relay_amplitude(L, D, nL, nD, X, nX, area, albedo, gain, phi: float = 1.0):
    """Third-bounce amplitude of a Lambertian element X (see the module equation)."""
    vL = X - L
    vD = X - D
    dL = norm3(vL)
    dD = norm3(vD)
    cos_L = dot3(vL, nL) / dL          # leaving L toward X
    cos_XL = -dot3(vL, nX) / dL        # arriving at X from L
    cos_XD = -dot3(vD, nX) / dD        # leaving X toward D
    cos_D = dot3(vD, nD) / dD          # arriving at D from X
    return (phi * gain * albedo / math.pi * form_factor(1.0, cos_L, cos_XL, dL)
            * form_factor(area, cos_XD, cos_D, dD))


_UNIT = GaussianIRF.from_sigma(1.0)


def deposit_window(amp, tau, left, width: float, sigma):
    """``amp * B(left - tau, width)`` for bins whose left edges are ``left``, through a Gaussian
    impulse response of std ``sigma`` (a number or a CasADi symbol: the width is fitted). The
    project's ``irf.bin_integral`` of the unit Gaussian at scaled offsets, since
    B_sigma(x, w) = B_1(x / sigma, w / sigma)."""
    return amp * bin_integral(_UNIT, (left - tau) / sigma, width / sigma)


def cell_spread(L, D, X, ta, tb, ha: float, hb: float):
    """Std of the path length over a grid cell of sides ha x hb with tangents ta, tb at X:
    tau varies linearly across it, tau_a = (u_XL + u_XD) . ta, so the delays spread as a box
    of variance (ha^2 tau_a^2 + hb^2 tau_b^2) / 12, added to the IRF's variance (moment
    matching; exact in the limit of a cell much smaller than the IRF width)."""
    uL = (X - L) / norm3(X - L)
    uD = (X - D) / norm3(X - D)
    g_a = dot3(uL + uD, ta)
    g_b = dot3(uL + uD, tb)
    return B.sqrt((ha * ha * g_a * g_a + hb * hb * g_b * g_b) / 12.0)
