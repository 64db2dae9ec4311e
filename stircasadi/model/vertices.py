"""Patches as path vertices: positions, normals, areas and BRDF parameters from theta.

A path vertex is a patch, or for an *extended* patch (a hidden square whose size the data may
resolve) one of its quadrature points: the patch is a disc of area a and radius R = sqrt(a/pi)
in the plane of its normal, sampled on equal-area rings,

    z_kq = z_k + R (u_q t1_k + v_q t2_k),     a_kq = a_k w_q,     sum_q w_q = 1,

with (t1, t2) the tangent frame of the (possibly rotating) normal (``radiometry.tangent_frame``)
and (u_q, v_q) the unit-disc points. A point patch is the one-point rule. Normals come from the
tilt unknowns, n = cos b (cos a n0 + sin a (ax x n0)) + sin b ax; an area may be an unknown,
fixed, or a calibrated pixel's footprint a = Omega r^2 / cos(theta) (Omega its solid angle,
r the range, theta the angle between the normal and the line of sight).

Everything is one formula for NumPy and CasADi (component triples, ``stircasadi.radiometry``).
Neglects: the disc's edge shape (a square of the same area differs at second order in its size).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .. import _backend as B
from ..radiometry import tangent_frame, vdot, vnorm, vsub

__all__ = ["disc_rule", "VertexLayout", "patch_quantities", "vertex_quantities"]


def disc_rule(rings: int, per_ring: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (u, v) on the unit disc and weights (sum 1): ``rings`` equal-area rings of
    ``per_ring`` points each, successive rings rotated by half a step. rings = 0: the centre."""
    if rings <= 0:
        return np.zeros(1), np.zeros(1), np.ones(1)
    u, v = [], []
    for r in range(rings):
        rad = math.sqrt((r + 0.5) / rings)
        for q in range(per_ring):
            ang = 2 * math.pi * (q + 0.5 * (r % 2)) / per_ring
            u.append(rad * math.cos(ang))
            v.append(rad * math.sin(ang))
    n = rings * per_ring
    return np.array(u), np.array(v), np.full(n, 1.0 / n)


@dataclass
class VertexLayout:
    """Which vertex belongs to which patch, and its disc coordinates."""

    patch: np.ndarray        # (V,) patch index of each vertex
    u: np.ndarray            # (V,) unit-disc coordinates (0 for point patches)
    v: np.ndarray
    w: np.ndarray            # (V,) area weight (1 for point patches)
    first: np.ndarray        # (M,) index of the patch's first vertex
    count: np.ndarray        # (M,) number of vertices of each patch

    @classmethod
    def build(cls, M: int, extended: dict) -> "VertexLayout":
        """``extended``: patch -> (rings, per_ring)."""
        P, U, Vv, W, first, count = [], [], [], [], np.zeros(M, int), np.zeros(M, int)
        for k in range(M):
            u, v, w = disc_rule(*extended[k]) if k in extended else (np.zeros(1), np.zeros(1), np.ones(1))
            first[k] = len(P)
            count[k] = len(u)
            P += [k] * len(u)
            U += u.tolist()
            Vv += v.tolist()
            W += w.tolist()
        return cls(np.array(P, int), np.array(U), np.array(Vv), np.array(W), first, count)

    @property
    def n(self) -> int:
        return len(self.patch)


def _rotated_normals(n0, ax, tilt, tilt2):
    """n = cos b (cos a n0 + sin a (ax x n0)) + sin b ax; n0, ax numeric (M, 3); tilt, tilt2
    arrays (M,) or CasADi (1, M). Returns a component triple."""
    u = np.cross(ax, n0)
    if B.is_symbolic(tilt, tilt2):
        ca_, sa, cb, sb = ca.cos(tilt), ca.sin(tilt), ca.cos(tilt2), ca.sin(tilt2)
        return tuple(cb * (ca_ * ca.DM(n0[:, i]).T + sa * ca.DM(u[:, i]).T) + sb * ca.DM(ax[:, i]).T
                     for i in range(3))
    a, b = np.asarray(tilt, float), np.asarray(tilt2, float)
    return tuple(np.cos(b) * (np.cos(a) * n0[:, i] + np.sin(a) * u[:, i]) + np.sin(b) * ax[:, i]
                 for i in range(3))


def patch_quantities(th: dict, model) -> dict:
    """Per-patch position, normal (component triples), area and BRDF parameters (rows) from the
    parameter values ``th`` (``ParameterSet.theta_sym`` or ``theta``)."""
    sym = B.is_symbolic(th["albedo"])
    row = (lambda e: e.T) if sym else (lambda e: np.asarray(e, float))
    if sym:
        Z = th["position"]
        z = (Z[0, :], Z[1, :], Z[2, :])
    else:
        Z = np.asarray(th["position"], float)
        z = (Z[:, 0], Z[:, 1], Z[:, 2])
    tilt, tilt2 = row(th["tilt"]), row(th["tilt2"])
    n = _rotated_normals(model.normals, model.tilt_axis, tilt, tilt2)
    area = row(th["area"])
    fp = model.footprint
    if np.isfinite(fp).any():  # calibrated pixels: a = Omega r^2 / cos, the area the pixel sees
        o = tuple(float(c) for c in model.camera)
        los = vsub(o, z)
        r = vnorm(los)
        cos_t = vdot(los, n) / r
        mask = np.isfinite(fp).astype(float)
        omega = np.where(np.isfinite(fp), fp, 0.0)
        if sym:
            mask, omega = ca.DM(mask).T, ca.DM(omega).T
        area = mask * (omega * r * r / B.fmax(cos_t, 1e-6)) + (1 - mask) * area
    return {"z": z, "n": n, "area": area, "albedo": row(th["albedo"]), "specular": row(th["specular"]),
            "exponent": row(th["exponent"])}


def vertex_quantities(pq: dict, layout: VertexLayout, model) -> dict:
    """The per-vertex arrays (component triples of length V) for the patch quantities ``pq``."""
    idx = layout.patch
    sym = B.is_symbolic(pq["albedo"])
    take = (lambda e: e[:, idx.tolist()]) if sym else (lambda e: np.asarray(e)[idx])
    z = tuple(take(c) for c in pq["z"])
    n = tuple(take(c) for c in pq["n"])
    area = take(pq["area"])
    ext = layout.count[idx] > 1
    if ext.any():
        refs = model.frame_ref[idx]                       # (V, 3) fixed reference directions
        ref = tuple(ca.DM(refs[:, i]).T for i in range(3)) if sym else tuple(refs[:, i] for i in range(3))
        t1, t2 = tangent_frame(n, ref)
        radius = B.sqrt(area / math.pi)
        uu = ca.DM(layout.u).T if sym else layout.u
        vv = ca.DM(layout.v).T if sym else layout.v
        off = tuple(radius * (uu * t1[i] + vv * t2[i]) for i in range(3))
        z = tuple(z[i] + off[i] for i in range(3))
    w = ca.DM(layout.w).T if sym else layout.w
    return {"z": z, "n": n, "area": area * w, "patch_area": area, "albedo": take(pq["albedo"]),
            "specular": take(pq["specular"]), "exponent": take(pq["exponent"])}
