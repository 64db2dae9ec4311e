"""The sensor: impulse response, binning and noise; turns an ideal ``Transient`` into a ``Capture``.

Deposition (no rounding bias)
-----------------------------
A light path of amplitude ``a`` arriving at exact path length ``tau`` adds to bin ``k`` (edges
``t_k, t_{k+1}``) the amount

    a * (H(t_{k+1} - tau) - H(t_k - tau)),        H = cumulative impulse response (unit area),

i.e. the bin integrates the impulse response centred on ``tau``. ``IdealIRF`` (no impulse
response) has H = step: the whole amplitude lands in the bin that contains tau. A bin therefore
holds time-integrated radiance (its sum over bins is the steady-state radiance).

Impulse responses
-----------------
``IdealIRF``, ``GaussianIRF`` (default FWHM 210 ps) and ``ArrayIRF`` live in ``stircasadi.irf``
(the bin integral above is written there once); this module imports them.

Noise (applied by ``Sensor.capture``, seeded)
---------------------------------------------
* ``GaussianNoise(sigma=..., relative=...)``: additive N(0, s^2) with
  ``s = sigma + relative * max|stir|``.
* ``PoissonNoise(photons)``: the STIR is scaled so its largest bin expects ``photons`` counts,
  counts are drawn, and the result is scaled back (so the mean is unchanged).
* ``background``: a constant added to every bin before noise (in STIR units; for Poisson in
  counts per bin).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from .capture import Capture
from .errors import SensorError
from .irf import ArrayIRF, GaussianIRF, IdealIRF, sampled
from .timegrid import TimeGrid

__all__ = ["Sensor", "GaussianNoise", "PoissonNoise"]

@dataclass(frozen=True)
class GaussianNoise:
    """Additive Gaussian noise, std = ``sigma + relative * max|stir|``."""

    sigma: float = 0.0
    relative: float = 0.0
    kind = "gaussian"

    def __post_init__(self):
        if self.sigma < 0 or self.relative < 0 or not (math.isfinite(self.sigma) and math.isfinite(self.relative)):
            raise SensorError(f"GaussianNoise sigma and relative must be >= 0; got {self.sigma}, {self.relative}.")

    def std(self, clean: np.ndarray) -> float:
        return self.sigma + self.relative * float(np.max(np.abs(clean))) if clean.size else self.sigma

    def apply(self, clean: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        s = self.std(clean)
        return clean + rng.normal(0.0, s, clean.shape), {"model": "gaussian", "sigma": s}


@dataclass(frozen=True)
class PoissonNoise:
    """Photon counting: the brightest bin expects ``photons`` counts."""

    photons: float = 1e4
    kind = "poisson"

    def __post_init__(self):
        if not (self.photons > 0) or not math.isfinite(self.photons):
            raise SensorError(f"PoissonNoise photons must be > 0; got {self.photons!r}.")

    def apply(self, clean: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
        if np.any(clean < -1e-12 * max(1e-300, float(np.max(np.abs(clean))))):
            raise SensorError("Poisson noise needs a non-negative signal; the STIR has negative bins.")
        peak = float(np.max(clean)) if clean.size else 0.0
        if peak <= 0:
            return clean.copy(), {"model": "poisson", "counts": 0.0, "scale": 0.0}
        scale = self.photons / peak
        counts = rng.poisson(np.clip(clean, 0, None) * scale)
        return counts / scale, {"model": "poisson", "counts": self.photons, "scale": scale}


@dataclass
class Sensor:
    """Impulse response + noise + background. ``Sensor()`` is ideal and noise-free.

    ``calibrated_camera=True`` models an intrinsically calibrated camera with a depth/normal
    channel: the Capture then records, for each observed patch, the unit ray direction from the
    camera (``extras['ray_directions']``), the surface normal (``extras['observed_normals']``),
    in the scene's frame, and the pixel's solid angle (``extras['pixel_solid_angle']``, sr: the
    patch is the pixel's footprint, area = Omega r^2 / cos). Positions still come from time of
    flight (distance along each ray).
    """

    irf: IdealIRF | GaussianIRF | ArrayIRF = field(default_factory=IdealIRF)
    noise: GaussianNoise | PoissonNoise | None = None
    background: float = 0.0
    calibrated_camera: bool = False

    def __post_init__(self):
        if not isinstance(self.irf, (IdealIRF, GaussianIRF, ArrayIRF)):
            raise SensorError(f"Sensor irf must be IdealIRF, GaussianIRF or ArrayIRF; got {type(self.irf).__name__}.")
        if self.noise is not None and not isinstance(self.noise, (GaussianNoise, PoissonNoise)):
            raise SensorError(f"Sensor noise must be GaussianNoise, PoissonNoise or None; got {type(self.noise).__name__}.")
        if not (self.background >= 0) or not math.isfinite(self.background):
            raise SensorError(f"Sensor background must be >= 0 and finite; got {self.background!r}.")

    @property
    def effects(self) -> dict:
        return {"irf": self.irf.describe(),
                "noise": "none" if self.noise is None else self.noise.kind,
                "background": self.background, "calibrated_camera": self.calibrated_camera}

    def irf_samples(self, grid: TimeGrid) -> np.ndarray | None:
        """The impulse response on the grid's bin width, peak at the centre (for the Capture file)."""
        return sampled(self.irf, grid.bin_width)

    def capture(self, transient, seed: int | None = 0, noise: bool = True) -> Capture:
        """Apply background and noise (seeded) to an ideal ``Transient``; return a ``Capture``."""
        rng = np.random.default_rng(seed)
        stir = transient.stir + self.background
        noise_attrs: dict = {"model": "none"}
        if noise and self.noise is not None:
            stir, noise_attrs = self.noise.apply(stir, rng)
        if self.background:
            noise_attrs["background"] = self.background
        noise_attrs["seed"] = -1 if seed is None else int(seed)
        scene = transient.scene
        extras = {}
        if self.calibrated_camera:
            if scene is None:
                raise SensorError("calibrated_camera needs the transient's scene to know the rays.")
            obs = np.asarray(transient.obs_ids)
            rays = scene.positions[obs] - scene.camera
            r = np.linalg.norm(rays, axis=1)
            extras["ray_directions"] = rays / r[:, None]
            extras["observed_normals"] = scene.normals[obs]
            # each pixel's solid angle: the patch's footprint seen from the camera
            cos_t = -np.sum(extras["ray_directions"] * scene.normals[obs], axis=1)
            extras["pixel_solid_angle"] = scene.areas[obs] * cos_t / r ** 2
        meta = dict(transient.metadata)
        meta.update(self.effects)
        meta["noise_applied"] = noise_attrs["model"]
        cap = Capture(
            grid=transient.grid, stir=stir, legs_included=transient.metadata.get("legs_included", True),
            source_xyz=scene.source if scene is not None else None,
            camera_xyz=scene.camera if scene is not None else None,
            illuminated_ids=transient.ill_ids, observed_ids=transient.obs_ids,
            irf=self.irf_samples(transient.grid), noise=noise_attrs,
            truth=scene.truth_dict() if scene is not None else None,
            provenance={"producer": "stircasadi.simulate", "scene": getattr(scene, "name", ""),
                        "method": meta.get("method", ""), "bounces": str(meta.get("bounces", ""))},
            extras=extras, metadata=meta)
        return cap
