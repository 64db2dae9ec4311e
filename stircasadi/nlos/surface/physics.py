"""Third-bounce relay transport of one hidden surface element: amplitude, delay, cell spread.

When to use: the analysis-by-synthesis surface fit (``stircasadi.nlos.surface``) evaluates this
on CasADi symbols (values and exact derivatives, mapped over (trace, node) pairs) and the
tests on NumPy arrays: one formula, two backends (STYLE.md rule 13). It calls the project's
``radiometry.form_factor``; the small backend-generic cosine and distance helpers written here
are what ``radiometry.cosines`` (NumPy only) lacks. The time response (how an amplitude at a
path length fills the bins) is ``response.py``.

Equations (DESIGN.md section 3 conventions; light of energy phi aimed at relay point L, the
camera reading the radiance of relay point D). A hidden element X (normal nX, area a, albedo
rho) adds to trace p the amplitude

    Lambertian:        A = phi g_p (rho / pi) F(1, cos_L, cos_XL, |X - L|) F(a, cos_XD, cos_D, |X - D|)
    retroreflective:   A = phi g_p (rho / pi) F(a, cos_L, cos_XL, |X - L|)          (confocal only)

where F(a, c1, c2, d) = a max(c1, 0) max(c2, 0) / d^2 is ``radiometry.form_factor`` (the area
of L cancels against the irradiance phi / a_L) and g_p = f(L) f(D) the relay BRDFs. A
retroreflector sends the light it receives back into a narrow cone around the direction it
came from: the whole cone lands in the laser's own wall spot, seen by the detector whatever the
distance, so the return leg has no 1/d^2 and no cosines (O'Toole et al. 2018: 1/r^2 instead of
1/r^4 for retroreflective scenes). It arrives at

    tau = leg_p + |X - L| + |X - D|.

Cell spread: the delay varies linearly across a grid cell of sides ha x hb with tangents ta, tb,
tau_a = (u_XL + u_XD) . ta, so the delays of the cell spread as a box of variance
c^2 = (ha^2 tau_a^2 + hb^2 tau_b^2) / 12, added to the response's Gaussian variance (moment
matching; exact in the limit of a cell much smaller than the response width).

Trace footprint: a trace that sums the returns of several scan points (a block of a confocal
scan, ``Relay.footprint``: position variances f_u, f_v along the relay frame's u, v, laser and
detection spot moving together) spreads the delays by the same first-order rule,
tau(L + e, D + e) ~ tau - (u_XL + u_XD) . e, so its variance
f^2 = f_u ((u_XL + u_XD) . u)^2 + f_v ((u_XL + u_XD) . v)^2 adds to c^2 (on the Stanford 40 cm
charts summed 4 x 4, f_u = f_v = (7.1 mm)^2: up to 13 mm of path at the scan's corners against
a response std of 4.7 mm).

Neglects: occlusion between hidden elements and of relay legs, hidden-to-hidden interreflection
(fourth and higher bounces), the variation of distances and cosines across an element, the
width of a retroreflector's cone (its return is assumed to land inside the detector's view).
"""
from __future__ import annotations

import math

import numpy as np

from ... import _backend as B
from ...radiometry import form_factor

__all__ = ["dot3", "norm3", "relay_amplitude", "relay_delay", "cell_variance", "footprint_variance", "BRDFS"]

BRDFS = ("lambertian", "retroreflective")


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


def relay_amplitude(L, D, nL, nD, X, nX, area, albedo, gain, phi: float = 1.0,
                    brdf: str = "lambertian"):
    """Third-bounce amplitude of an element X (see the module equations)."""
    vL = X - L
    dL = norm3(vL)
    cos_L = dot3(vL, nL) / dL          # leaving L toward X
    cos_XL = -dot3(vL, nX) / dL        # arriving at X from L
    if brdf == "retroreflective":
        return phi * gain * albedo / math.pi * form_factor(area, cos_L, cos_XL, dL)
    vD = X - D
    dD = norm3(vD)
    cos_XD = -dot3(vD, nX) / dD        # leaving X toward D
    cos_D = dot3(vD, nD) / dD          # arriving at D from X
    return (phi * gain * albedo / math.pi * form_factor(1.0, cos_L, cos_XL, dL)
            * form_factor(area, cos_XD, cos_D, dD))


def cell_variance(L, D, X, ta, tb, ha: float, hb: float):
    """Variance of the path length over a grid cell (see the module docstring): the delay's
    first-order spread over a box of sides ha x hb along ta, tb (variances ha^2 / 12, hb^2 / 12)."""
    return footprint_variance(L, D, X, ta, tb, ha * ha / 12.0, hb * hb / 12.0)


def footprint_variance(L, D, X, u, v, fu2, fv2):
    """Variance of the path length when X's or the trace's spots' position spreads with variances
    ``fu2``, ``fv2`` along ``u``, ``v`` (a trace's footprint, or a node's cell: see the module
    docstring); first order in the spread, the delay's gradient u_XL + u_XD."""
    g = (X - L) / norm3(X - L) + (X - D) / norm3(X - D)
    g_u = dot3(g, u)
    g_v = dot3(g, v)
    return fu2 * g_u * g_u + fv2 * g_v * g_v
