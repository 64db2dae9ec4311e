"""Helpers shared by the problem scripts (grids of patches, default sensor, a standard main)."""
from __future__ import annotations

import numpy as np

from stircasadi.brdf import Lambertian
from stircasadi.scene import Patch
from stircasadi.irf import GaussianIRF
from stircasadi.sensor import GaussianNoise, Sensor


def unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v)


def plane_patches(centre, normal, u_axis, n_u: int, n_v: int, spacing: float, area: float,
                  brdf=None, albedos=None, hidden: bool = False, prefix: str = "") -> list[Patch]:
    """An n_u x n_v grid of patches on the plane through ``centre`` with unit ``normal``."""
    n = unit(normal)
    u = unit(np.asarray(u_axis, float) - np.dot(u_axis, n) * n)
    v = np.cross(n, u)
    out = []
    for a in range(n_u):
        for b in range(n_v):
            c = np.asarray(centre, float) + (a - (n_u - 1) / 2) * spacing * u + (b - (n_v - 1) / 2) * spacing * v
            br = brdf if albedos is None else Lambertian(float(albedos[len(out)]))
            out.append(Patch(tuple(c), tuple(n), area, br or Lambertian(0.7), hidden=hidden,
                             name=f"{prefix}{a}_{b}"))
    return out


def gaussian_sensor(noise_rel: float, fwhm_ps: float, calibrated_camera: bool = False) -> Sensor:
    """Gaussian impulse response of ``fwhm_ps`` and Gaussian noise ``noise_rel`` x peak (none at 0)."""
    return Sensor(irf=GaussianIRF.from_ps(fwhm_ps),
                  noise=GaussianNoise(relative=noise_rel) if noise_rel > 0 else None,
                  calibrated_camera=calibrated_camera)


def paper_sensor(noise_rel: float = 1e-4, calibrated_camera: bool = False) -> Sensor:
    """The paper's 210 ps FWHM response (photodiode + 5 GHz scope) and Gaussian noise."""
    return gaussian_sensor(noise_rel, 210.0, calibrated_camera)
