"""BRDFs: Lambertian, modified Phong, ideal mirror; one formula for NumPy and CasADi.

When to use
-----------
Each patch carries one BRDF object. The transport code asks for ``value(cos_in, cos_out,
cos_io)``: the BRDF in 1/sr for light arriving from direction ``w_in`` and leaving toward
``w_out`` (both unit vectors pointing *away* from the surface), written only through

    cos_in  = n . w_in,     cos_out = n . w_out,     cos_io = w_in . w_out,

so the same expression evaluates on NumPy arrays (numeric forward model) and on CasADi symbols
(the symbolic model of the estimator). The cosine of the angle between ``w_out`` and the mirror
direction of ``w_in`` is ``cos_alpha = 2 cos_in cos_out - cos_io``.

Equations
---------
* Lambertian: ``f = rho / pi``, ``0 <= rho <= 1``.
* Modified Phong (Lafortune & Willems 1994, "Using the modified Phong reflectance model for
  physically based rendering"):
  ``f = kd / pi + ks (n + 2) / (2 pi) max(cos_alpha, 0)^n``.
  Its directional-hemispherical albedo is at most ``kd + ks``, so the model conserves energy
  iff ``kd + ks <= 1`` (checked here, and a hard NLP constraint in the estimator).
* Ideal mirror of reflectance R: ``f = R delta(w_out - mirror(w_in)) / cos_out``. A delta cannot
  be sampled between small patches, so the transport code treats a mirror patch as a window
  through which the receiver sees the mirror image of the emitter (image-source method, see
  ``Mirror.transfer``). What this neglects: diffraction, the mirror's finite aperture beyond the
  patch disc, and Fresnel angle dependence of R.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import _backend as B
from .errors import BRDFError

_INV_PI = 1.0 / math.pi


def _check_unit_interval(name: str, v: float) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError) as exc:
        raise BRDFError(f"{name} must be a number in [0, 1]; got {v!r}.") from exc
    if not (0.0 <= v <= 1.0) or math.isnan(v):
        raise BRDFError(f"{name} must lie in [0, 1] (fraction of energy reflected); got {v}.")
    return v


@dataclass(frozen=True)
class Lambertian:
    """Ideal diffuse reflector, ``f = albedo / pi``."""

    albedo: float = 0.8
    kind = "lambertian"
    glossy = False

    def __post_init__(self):
        object.__setattr__(self, "albedo", _check_unit_interval("Lambertian albedo", self.albedo))

    @staticmethod
    def formula(cos_in, cos_out, cos_io, albedo):
        """Elementwise BRDF value (1/sr); parameters may be symbolic."""
        return albedo * _INV_PI + 0.0 * cos_in

    def value(self, cos_in, cos_out, cos_io):
        return self.formula(cos_in, cos_out, cos_io, self.albedo)

    @property
    def params(self) -> dict:
        return {"albedo": self.albedo}

    @property
    def diffuse_albedo(self) -> float:
        return self.albedo


@dataclass(frozen=True)
class Phong:
    """Modified (energy-conserving) Phong: ``kd/pi + ks (n+2)/(2 pi) max(cos_alpha,0)^n``.

    Parameters
    ----------
    albedo : float
        Diffuse albedo ``kd`` in [0, 1].
    specular : float
        Specular reflectance ``ks`` in [0, 1], with ``kd + ks <= 1``.
    exponent : float
        Phong exponent ``n >= 0`` (larger = glossier).
    """

    albedo: float = 0.5
    specular: float = 0.3
    exponent: float = 20.0
    kind = "phong"
    glossy = True

    def __post_init__(self):
        kd = _check_unit_interval("Phong albedo (kd)", self.albedo)
        ks = _check_unit_interval("Phong specular (ks)", self.specular)
        if kd + ks > 1.0 + 1e-12:
            raise BRDFError(f"Phong albedo + specular must be <= 1 for energy conservation; got "
                            f"{kd} + {ks} = {kd + ks}. Lower one of them.")
        n = float(self.exponent)
        if not (n >= 0) or not math.isfinite(n):
            raise BRDFError(f"Phong exponent must be a finite number >= 0; got {self.exponent!r}.")
        object.__setattr__(self, "albedo", kd)
        object.__setattr__(self, "specular", ks)
        object.__setattr__(self, "exponent", n)

    @staticmethod
    def formula(cos_in, cos_out, cos_io, albedo, specular, exponent):
        """Elementwise BRDF value (1/sr); parameters may be symbolic."""
        cos_alpha = 2.0 * cos_in * cos_out - cos_io
        lobe = B.power(B.fmax(cos_alpha, 0.0), exponent)
        return albedo * _INV_PI + specular * (exponent + 2.0) * (0.5 * _INV_PI) * lobe

    def value(self, cos_in, cos_out, cos_io):
        return self.formula(cos_in, cos_out, cos_io, self.albedo, self.specular, self.exponent)

    @property
    def params(self) -> dict:
        return {"albedo": self.albedo, "specular": self.specular, "exponent": self.exponent}

    @property
    def diffuse_albedo(self) -> float:
        return self.albedo


@dataclass(frozen=True)
class Mirror:
    """Ideal planar mirror of reflectance ``R`` (image-source transfer between small patches)."""

    reflectance: float = 0.95
    kind = "mirror"
    glossy = True

    def __post_init__(self):
        object.__setattr__(self, "reflectance",
                           _check_unit_interval("Mirror reflectance", self.reflectance))

    def value(self, cos_in, cos_out, cos_io):
        """A mirror has no finite BRDF value; the transport uses ``transfer`` instead."""
        return 0.0 * cos_in

    @property
    def params(self) -> dict:
        return {"reflectance": self.reflectance}

    @property
    def diffuse_albedo(self) -> float:
        return 0.0

    @staticmethod
    def transfer(src, mirror_c, mirror_n, mirror_area, dst, reflectance):
        """Specular transfer through a mirror patch (image-source method), NumPy only.

        Light leaving a point ``src`` reaches ``dst`` via the mirror patch (centre ``mirror_c``,
        unit normal ``mirror_n``, area ``mirror_area``, modelled as a disc) iff the segment from
        the mirror image ``src'`` of ``src`` to ``dst`` crosses the disc. Arrays broadcast over
        leading axes (last axis = xyz).

        Returns
        -------
        hit : bool array
            Whether the specular path exists.
        path_len : array
            Length of the specular path ``|src' - dst|`` (= src->mirror->dst through the hit point).
        factor : array
            ``R`` where hit, else 0. The receiver's irradiance is
            ``factor * L_src * a_src cos(theta_src) cos(theta_dst) / path_len**2`` (radiance is
            conserved along the reflected ray; the emitter is seen at distance ``path_len``).
        cos_src, cos_dst : arrays
            Cosines at the emitter (toward the hit point) and at the receiver.
        hit_point : array
            Where the ray meets the mirror plane.
        """
        src, mirror_c, mirror_n, dst = (np.asarray(a, float) for a in (src, mirror_c, mirror_n, dst))
        h_src = np.sum((src - mirror_c) * mirror_n, axis=-1)
        h_dst = np.sum((dst - mirror_c) * mirror_n, axis=-1)
        image = src - 2.0 * h_src[..., None] * mirror_n
        seg = dst - image
        path_len = np.linalg.norm(seg, axis=-1)
        denom = h_dst + h_src  # both in front: the segment crosses the plane at s = h_src/(h_src+h_dst)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(denom > 0, h_src / np.where(denom > 0, denom, 1.0), -1.0)
        hit_point = image + s[..., None] * seg
        radius = np.sqrt(np.asarray(mirror_area, float) / math.pi)
        off = np.linalg.norm(hit_point - mirror_c, axis=-1)
        hit = (h_src > 0) & (h_dst > 0) & (s > 0) & (s < 1) & (off <= radius)
        factor = np.where(hit, reflectance, 0.0)
        return hit, path_len, factor, hit_point


BRDF = Lambertian | Phong | Mirror


def brdf_from_params(kind: str, **params) -> BRDF:
    """Build a BRDF by name: ``lambertian`` (albedo), ``phong`` (albedo, specular, exponent),
    ``mirror`` (reflectance)."""
    table = {"lambertian": Lambertian, "phong": Phong, "mirror": Mirror}
    if kind not in table:
        raise BRDFError(f"Unknown BRDF kind {kind!r}; allowed: {sorted(table)}.")
    return table[kind](**params)
