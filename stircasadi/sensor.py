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
* ``IdealIRF()``: no blur.
* ``GaussianIRF(fwhm)``: H(x) = Phi(x / sigma), sigma = fwhm / (2 sqrt(2 ln 2)). The default
  FWHM is 210 ps of time (6.3 cm of path), the paper's photodiode + 5 GHz sampling scope.
* ``ArrayIRF(samples, bin_width)``: a measured response sampled on bins of ``bin_width`` with
  its peak at the centre sample, taken as piecewise constant (H piecewise linear).

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
from scipy.special import ndtr

from .capture import Capture
from .constants import ps_to_m
from .errors import SensorError
from .timegrid import TimeGrid

_FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def _discrete_kernel(irf, bin_width: float) -> tuple[np.ndarray, int]:
    """Kernel ``h[m] = H((m+1) w) - H(m w)`` over the response's support, and the index of m = 0:
    how a path at a bin's left edge spreads over bins (integer-delay mode)."""
    lo, hi = irf.support()
    m = np.arange(math.floor(lo / bin_width) - 1, math.ceil(hi / bin_width) + 1)
    return irf.cdf((m + 1) * bin_width) - irf.cdf(m * bin_width), int(-m[0])


class IdealIRF:
    """No impulse response: each path lands in the bin that contains it."""

    kind = "ideal"
    band_limited = False

    def cdf(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x) > 0).astype(float)

    def support(self) -> tuple[float, float]:
        return (0.0, 0.0)

    def discrete(self, bin_width: float) -> tuple[np.ndarray, int]:
        """Kernel ``h[m]`` (m = -offset..) for a path at a bin's left edge (integer mode)."""
        return np.array([1.0]), 0

    def describe(self) -> str:
        return "none"


@dataclass(frozen=True)
class GaussianIRF:
    """Gaussian impulse response of full width at half maximum ``fwhm`` (metres of path)."""

    fwhm: float = ps_to_m(210.0)
    kind = "gaussian"
    band_limited = True

    def __post_init__(self):
        if not (self.fwhm > 0) or not math.isfinite(self.fwhm):
            raise SensorError(f"GaussianIRF fwhm must be > 0 metres of path; got {self.fwhm!r}. "
                              "For picoseconds use GaussianIRF.from_ps(fwhm_ps).")

    @classmethod
    def from_ps(cls, fwhm_ps: float) -> "GaussianIRF":
        return cls(ps_to_m(fwhm_ps))

    @property
    def sigma(self) -> float:
        return self.fwhm * _FWHM_TO_SIGMA

    def cdf(self, x):
        return ndtr(np.asarray(x) / self.sigma)

    def support(self) -> tuple[float, float]:
        return (-8.3 * self.sigma, 8.3 * self.sigma)  # tail mass < 1e-16

    def fourier(self, omega: np.ndarray) -> np.ndarray:
        """Fourier transform of the (centred) density, exp(-sigma^2 omega^2 / 2)."""
        return np.exp(-0.5 * (self.sigma * omega) ** 2)

    def band_limit(self, tol: float = 1e-15) -> float:
        """Angular frequency (rad per metre) above which the spectrum is below ``tol``."""
        return math.sqrt(-2.0 * math.log(tol)) / self.sigma

    def discrete(self, bin_width: float) -> tuple[np.ndarray, int]:
        return _discrete_kernel(self, bin_width)

    def describe(self) -> str:
        return f"gaussian fwhm={self.fwhm:.4g} m"


@dataclass(frozen=True)
class ArrayIRF:
    """A measured impulse response sampled on bins of ``bin_width``, peak at the centre sample."""

    samples: tuple
    bin_width: float
    kind = "array"
    band_limited = False

    def __post_init__(self):
        s = np.asarray(self.samples, dtype=float)
        if s.ndim != 1 or s.size == 0 or not np.all(np.isfinite(s)) or s.sum() <= 0 or np.any(s < 0):
            raise SensorError("ArrayIRF samples must be a non-empty 1-D array of finite, non-negative "
                              f"values with a positive sum; got shape {s.shape}.")
        if not (self.bin_width > 0):
            raise SensorError(f"ArrayIRF bin_width must be > 0 metres; got {self.bin_width!r}.")
        object.__setattr__(self, "samples", tuple((s / s.sum()).tolist()))

    @property
    def _knots(self):
        s = np.asarray(self.samples)
        c = (len(s) - 1) / 2.0
        x = (np.arange(len(s) + 1) - c - 0.5) * self.bin_width
        return x, np.concatenate([[0.0], np.cumsum(s)])

    def cdf(self, x):
        xk, yk = self._knots
        return np.interp(np.asarray(x, float), xk, yk, left=0.0, right=1.0)

    def support(self) -> tuple[float, float]:
        xk, _ = self._knots
        return (float(xk[0]), float(xk[-1]))

    def discrete(self, bin_width: float) -> tuple[np.ndarray, int]:
        return _discrete_kernel(self, bin_width)

    def describe(self) -> str:
        return f"measured ({len(self.samples)} samples)"


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
    camera (``extras['ray_directions']``) and the surface normal (``extras['observed_normals']``),
    in the scene's frame. Positions still come from time of flight (distance along each ray).
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
        if isinstance(self.irf, IdealIRF):
            return None
        lo, hi = self.irf.support()
        half = int(math.ceil(max(-lo, hi) / grid.bin_width))
        k = np.arange(-half, half + 1)
        x = k * grid.bin_width
        return self.irf.cdf(x + 0.5 * grid.bin_width) - self.irf.cdf(x - 0.5 * grid.bin_width)

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
            extras["ray_directions"] = rays / np.linalg.norm(rays, axis=1)[:, None]
            extras["observed_normals"] = scene.normals[obs]
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
