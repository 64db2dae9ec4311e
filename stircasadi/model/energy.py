"""The energy-conservation terms of a set-up ``TransientModel``: symbolic flux-transfer sums.

For every patch k, c_k = sum_r rho_r F_{k->r} (F the fraction of k's diffuse emission that lands
on r, from ``radiometry.direct_leg``); max_k c_k < 1 bounds the spectral radius of the transport
below 1, so the estimated scene conserves energy (``joint.constraints`` makes it a hard
constraint).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from ..radiometry import direct_leg
from .vertices import patch_quantities

__all__ = ["flux_column_sums"]


def flux_column_sums(model):
    """Symbolic flux-transfer column sums c_k = sum_r rho_r F_{k->r} (M,), F the fraction of
    k's diffuse emission landing on r; max_k c_k < 1 bounds the transport's spectral radius
    below 1 (stable, energy-conserving). rho = albedo (+ specular for Phong; albedo / area
    where the unknown is the product)."""
    pq = patch_quantities(model.theta_sym, model)
    h, r = np.nonzero(model.visibility)
    if not len(h):
        return ca.MX.zeros(model.M, 1)
    z = pq["z"]
    nn = pq["n"]
    tk = lambda e, i: e[:, i.tolist()]  # noqa: E731
    leg = direct_leg(tuple(tk(c, h) for c in z), tuple(tk(c, r) for c in z),
                     tuple(tk(c, h) for c in nn), tuple(tk(c, r) for c in nn), tk(pq["area"], r))
    rho = pq["albedo"]
    mk = ca.DM(model.albedo_product.astype(float)).T
    rho = mk * rho / pq["area"] + (1 - mk) * rho + pq["specular"] * ca.DM(model.glossy.astype(float)).T
    terms = leg.g / math.pi * tk(rho, r)
    S = ca.DM(ca.Sparsity.triplet(model.M, len(h), h.tolist(), list(range(len(h)))), np.ones(len(h)))
    return ca.mtimes(S, terms.T)
