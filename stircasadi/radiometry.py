"""The radiometric formulas of the small-patch transient rendering equation, written once.

Every function here evaluates on NumPy arrays and on CasADi symbols alike (STYLE.md rule 13):
the numeric forward model (``stircasadi.transport``) and the symbolic model of the estimator
(``stircasadi.model``) both call them, so an effect (a mirror, a glossy lobe) exists in both or
in neither. Vectors are passed as **component triples** ``(x, y, z)`` whose entries are arrays of
any matching shape (NumPy ``(P,)`` or CasADi ``(1, P)``); ``vec``/``cols`` convert.

Convention (DESIGN.md section 3): patch ``i`` has centre z_i, unit normal n_i, area a_i and
BRDF f_i (1/sr). The source sends a pulse of energy ``phi`` that lands wholly on the aimed
patch (irradiance ``phi / a_i``). Patch k lights patch i through the small-patch form factor

    G_ki = a_k max(cos theta_k, 0) max(cos theta_i, 0) / d_ki^2

so the irradiance at i is ``L_ki * G_ki`` where ``L_ki`` is the radiance leaving k toward i,
and the radiance leaving i toward j is ``f_i(w_in, w_out) * irradiance``. A leg of length d
delays by d metres of optical path. A mirror patch m of reflectance R is no vertex of a path: it
turns a leg k -> i into the image-source leg ``k' -> i`` (k' = k mirrored in m's plane) of length
|k' - z_i| and form factor ``R G`` with the cosines of the reflected ray (``mirror_leg``).

Neglects: the variation of d and the cosines across a patch (valid while d >> sqrt(a)),
polarisation, participating media, wavelength, diffraction at mirror edges.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _backend as B

__all__ = ["form_factor", "source_irradiance", "cosines", "Leg", "direct_leg", "mirror_leg",
           "facing_matrix", "perpendicular", "tangent_frame", "vdot", "vsub", "vscale",
           "vnorm", "vec", "rows"]


# ----------------------------------------------------------------------------- vector triples
def vsub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def vscale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


def vdot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def vnorm(a):
    return B.sqrt(vdot(a, a))


def vcross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def vec(X):
    """Component triple of an array of vectors: NumPy (..., 3) -> its columns; CasADi (3, P) ->
    its rows (1, P)."""
    if B.is_symbolic(X):
        return (X[0, :], X[1, :], X[2, :])
    X = np.asarray(X, float)
    return (X[..., 0], X[..., 1], X[..., 2])


def rows(t):
    """NumPy (..., 3) array from a numeric component triple."""
    return np.stack([np.asarray(c, float) for c in t], axis=-1)


# ----------------------------------------------------------------------------- scalar formulas
def form_factor(area_src, cos_src, cos_dst, dist):
    """Small-patch geometric transfer ``a_src max(cos_src,0) max(cos_dst,0) / d^2``."""
    return area_src * B.fmax(cos_src, 0.0) * B.fmax(cos_dst, 0.0) / (dist * dist)


def source_irradiance(phi, area):
    """Irradiance on the aimed patch from a collimated pulse of energy ``phi`` landing wholly on it."""
    return phi / area


def cosines(d_vec_src_to_dst, n_src, n_dst, dist):
    """(cos_src, cos_dst) for a leg from src to dst with unit normals; NumPy arrays (..., 3)."""
    u = np.asarray(d_vec_src_to_dst, float) / np.asarray(dist, float)[..., None]
    return np.sum(u * n_src, axis=-1), -np.sum(u * n_dst, axis=-1)


# ----------------------------------------------------------------------------- legs
@dataclass
class Leg:
    """One leg of a light path (component triples and arrays of one backend).

    length : path length of the leg (metres); g : form factor (times R through a mirror);
    dir_out : unit direction leaving the emitting patch; dir_in : unit direction at the
    receiving patch pointing back toward where the light came from.
    """

    length: object
    g: object
    dir_out: tuple
    dir_in: tuple


def direct_leg(z_src, z_dst, n_src, n_dst, area_src) -> Leg:
    """The leg from patch centre ``z_src`` straight to ``z_dst`` (component triples)."""
    v = vsub(z_dst, z_src)
    d = vnorm(v)
    u = vscale(v, 1.0 / d)
    c_src, c_dst = vdot(u, n_src), -vdot(u, n_dst)
    return Leg(d, form_factor(area_src, c_src, c_dst, d), u, vscale(u, -1.0))


def mirror_leg(z_src, z_dst, n_src, n_dst, area_src, m_centre, m_normal, reflectance) -> Leg:
    """The image-source leg src -> mirror -> dst (the mirror's plane through ``m_centre`` with unit
    ``m_normal``). Whether the reflected ray meets the mirror patch is decided numerically by
    ``stircasadi.brdf.Mirror.transfer`` where the leg is built; this gives its length, form
    factor (times the reflectance) and directions."""
    h = vdot(vsub(z_src, m_centre), m_normal)
    image = vsub(z_src, vscale(m_normal, 2.0 * h))
    v = vsub(z_dst, image)
    L = vnorm(v)
    u = vscale(v, 1.0 / L)                                  # the ray from the image to dst
    u1 = vsub(u, vscale(m_normal, 2.0 * vdot(u, m_normal)))  # the ray leaving src toward the mirror
    c_src, c_dst = vdot(u1, n_src), -vdot(u, n_dst)
    return Leg(L, reflectance * form_factor(area_src, c_src, c_dst, L), u1, vscale(u, -1.0))


# ----------------------------------------------------------------------------- numeric helpers
def facing_matrix(z: np.ndarray, n: np.ndarray) -> np.ndarray:
    """(M, M) bool: patches k and i face each other (both cosines > 0); diagonal False.
    Occlusion is not tested here (``Scene.patch_visibility`` adds ray casting)."""
    z, n = np.asarray(z, float), np.asarray(n, float)
    vec_ = z[None, :, :] - z[:, None, :]
    d = np.linalg.norm(vec_, axis=-1)
    np.fill_diagonal(d, 1.0)
    u = vec_ / d[..., None]
    ck = np.einsum("kid,kd->ki", u, n)
    ci = -np.einsum("kid,id->ki", u, n)
    vis = (ck > 0) & (ci > 0)
    np.fill_diagonal(vis, False)
    return vis


def perpendicular(n) -> np.ndarray:
    """A unit vector perpendicular to the unit vector n (from the axis least aligned with n)."""
    n = np.asarray(n, float)
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    v = e - np.dot(e, n) * n
    return v / np.linalg.norm(v)


def tangent_frame(n, ref):
    """Two unit tangents (t1, t2) of the plane with unit normal ``n`` (component triples, any
    backend): t1 = normalise(ref x n), t2 = n x t1, for a fixed reference direction ``ref``
    (a component triple) not parallel to n. Smooth in n, so it can follow a rotating normal."""
    t = vcross(ref, n)
    t1 = vscale(t, 1.0 / vnorm(t))
    return t1, vcross(n, t1)
