"""The radiometric formulas of the small-patch transient rendering equation, written once.

All functions are elementwise and accept NumPy arrays or CasADi symbols (STYLE.md rule 13);
the numeric forward model (``stircasadi.transport``) and the symbolic model
(``stircasadi.model``) both call them.

Convention (DESIGN.md section 3): patch ``i`` has centre z_i, unit normal n_i, area a_i and
BRDF f_i (1/sr). The source sends a pulse of energy ``phi`` that lands wholly on the aimed
patch (irradiance ``phi / a_i``). Patch k lights patch i through the small-patch form factor

    G_ki = a_k cos(theta_k) cos(theta_i) v_ki / d_ki^2                    (sr-weighted, m^0)

so the irradiance at i is ``L_ki * G_ki`` where ``L_ki`` is the radiance leaving k toward i,
and the radiance leaving i toward j is ``f_i(w_in, w_out) * irradiance``. Every leg of length d
delays by d metres of optical path. Neglected: the variation of d and the cosines across a
patch (valid while d >> sqrt(a)), polarisation, participating media, wavelength.
"""
from __future__ import annotations

from . import _backend as B


def form_factor(area_src, cos_src, cos_dst, dist):
    """Small-patch geometric transfer ``a_src max(cos_src,0) max(cos_dst,0) / d^2``."""
    return area_src * B.fmax(cos_src, 0.0) * B.fmax(cos_dst, 0.0) / (dist * dist)


def source_irradiance(phi, area):
    """Irradiance on the aimed patch from a collimated pulse of energy ``phi`` landing wholly on it."""
    return phi / area


def cosines(d_vec_src_to_dst, n_src, n_dst, dist):
    """(cos_src, cos_dst) for a leg from src to dst with unit normals; NumPy arrays (...,3)."""
    import numpy as np

    u = d_vec_src_to_dst / dist[..., None]
    return np.sum(u * n_src, axis=-1), -np.sum(u * n_dst, axis=-1)
