"""``CaptureView``: a Capture unpacked once for the estimators (ids, frames, calibration, IRF, noise).

Every stage of the inverse route reads the capture through this one view, so the fallbacks
(source at the origin, camera = source), the id <-> row/column maps, the impulse response and
the noise level are decided in one place. **It never reads ``capture.truth``.**

What a capture can tell the estimator beyond its traces:

* ``observed_xyz`` / ``illuminated_xyz``: the visible points (a relay wall, a scanned scene);
* ``ray_directions`` (n_obs, 3): a calibrated camera's pixel rays (positions = camera + range x ray);
* ``observed_normals`` (n_obs, 3): the surface normals a calibrated depth/normal camera measures;
* ``pixel_solid_angle`` (n_obs,): each calibrated pixel's solid angle, so a visible patch's area
  is its footprint Omega r^2 / cos(theta);
* group ``priors/`` (attributes): declared knowledge of the experiment — ``flatland`` (every
  patch lies in the plane of the source and the visible patches), ``areas`` (JSON {id: m^2}).
  The user's command-line priors (``--areas``, ``--flatland``) are merged on top.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from .errors import CaptureError
from .irf import IdealIRF, Template, estimate_samples, from_samples

__all__ = ["CaptureView", "noise_from_data"]


def noise_from_data(traces: np.ndarray) -> float:
    """Robust noise std of the traces from their first differences pooled over all traces
    (MAD / 0.6745 / sqrt 2): the returns occupy few bins, so their slopes barely move the median."""
    d = np.diff(np.asarray(traces, float), axis=-1).ravel()
    if d.size < 16:
        return 0.0
    med = np.median(d)
    return float(np.median(np.abs(d - med)) / 0.6745 / np.sqrt(2.0))


@dataclass
class CaptureView:
    """See the module docstring. Build with ``CaptureView.of(capture, priors)``."""

    capture: object
    ids: np.ndarray                 # visible ids (illuminated or observed), sorted
    ill: np.ndarray                 # STIR row ids
    obs: np.ndarray                 # STIR column ids
    source: np.ndarray
    camera: np.ndarray
    source_given: bool
    known_xyz: np.ndarray           # (M, 3) NaN where unknown
    rays: np.ndarray                # (M, 3) NaN where unknown
    known_normals: np.ndarray       # (M, 3) NaN where unknown
    solid_angle: np.ndarray         # (M,) NaN where unknown
    irf: object
    irf_source: str
    capture_sigma: float | None
    noise_model: str
    poisson_scale: float | None
    priors: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ construction
    @classmethod
    def of(cls, capture, priors: dict | None = None) -> "CaptureView":
        ill, obs = np.asarray(capture.ill_ids(), int), np.asarray(capture.obs_ids(), int)
        ids = np.union1d(ill, obs)
        src_given = capture.source_xyz is not None
        src = np.asarray(capture.source_xyz, float) if src_given else np.zeros(3)
        cam = np.asarray(capture.camera_xyz, float) if capture.camera_xyz is not None else src.copy()
        M = len(ids)
        pos = {int(v): k for k, v in enumerate(ids)}
        known = np.full((M, 3), np.nan)
        for xyz, which in ((capture.observed_xyz, obs), (capture.illuminated_xyz, ill)):
            if xyz is not None:
                for r, i in enumerate(which):
                    known[pos[int(i)]] = xyz[r]
        ex = capture.extras if isinstance(capture.extras, dict) else {}
        rays = np.full((M, 3), np.nan)
        nrm = np.full((M, 3), np.nan)
        om = np.full(M, np.nan)
        for key, arr, width in (("ray_directions", rays, 3), ("observed_normals", nrm, 3),
                                ("pixel_solid_angle", om, 1)):
            v = ex.get(key)
            if v is None:
                continue
            v = np.asarray(v, float)
            want = (len(obs), 3) if width == 3 else (len(obs),)
            if v.shape != want or not np.all(np.isfinite(v)):
                raise CaptureError(f"Capture dataset '{key}' must be finite with shape {want} (one per "
                                   f"observed patch); got shape {v.shape}.")
            if width == 3:
                nv = np.linalg.norm(v, axis=1)
                if np.any(nv < 1e-12):
                    raise CaptureError(f"Capture dataset '{key}' holds a zero vector; give unit vectors.")
                v = v / nv[:, None]
            elif np.any(v <= 0):
                raise CaptureError("Capture dataset 'pixel_solid_angle' must be > 0 sr.")
            for c, j in enumerate(obs):
                arr[pos[int(j)]] = v[c]
        irf, irf_source = cls._irf(capture)
        noise = capture.noise if isinstance(capture.noise, dict) else {}
        model = str(noise.get("model", "unknown")).lower()
        sig = noise.get("sigma")
        try:
            sig = float(sig) if sig is not None else None
        except (TypeError, ValueError) as exc:
            raise CaptureError(f"Capture noise attribute 'sigma' must be a number (STIR units); got "
                               f"{sig!r}.") from exc
        if sig is not None and not (np.isfinite(sig) and sig >= 0):
            raise CaptureError(f"Capture noise attribute 'sigma' must be >= 0 and finite; got {sig!r}.")
        scale = noise.get("scale")
        pri = cls._capture_priors(ex)
        pri.update(priors or {})
        return cls(capture, ids, ill, obs, src, cam, src_given, known, rays, nrm, om, irf, irf_source,
                   sig if (model == "gaussian" and sig) else None, model,
                   float(scale) if (model == "poisson" and scale) else None, pri)

    @staticmethod
    def _irf(capture):
        w = capture.grid.bin_width
        if capture.irf is not None:
            return from_samples(capture.irf, w), "capture"
        if capture.stir is not None:
            common = np.intersect1d(capture.ill_ids(), capture.obs_ids())
            if common.size:
                s = estimate_samples(np.stack([capture.trace(i, i) for i in common]))
                if s is not None:
                    return from_samples(s, w), "estimated from first-bounce returns"
        return IdealIRF(), "none (no samples, none estimated)"

    @staticmethod
    def _capture_priors(ex) -> dict:
        g = ex.get("priors")
        if not isinstance(g, dict):
            return {}
        attrs = dict(g.get("__attrs__", {}))
        out = {}
        if "flatland" in attrs:
            out["flatland"] = bool(attrs["flatland"])
        if "areas" in attrs:
            try:
                out["areas"] = {int(k): float(v) for k, v in json.loads(attrs["areas"]).items()}
            except (ValueError, TypeError, AttributeError) as exc:
                raise CaptureError(f"Capture priors attribute 'areas' must be JSON {{id: m^2}}; got "
                                   f"{attrs['areas']!r}.") from exc
        return out

    # ------------------------------------------------------------------ views
    @property
    def M(self) -> int:
        return len(self.ids)

    @property
    def grid(self):
        return self.capture.grid

    @property
    def radiometric(self) -> bool:
        """Whether the STIR is in the model's radiance units with a unit pulse (a stircasadi
        simulation, or attribute ``radiometric_unit``); else its gain is one more unknown."""
        prov = self.capture.provenance or {}
        ex = self.capture.extras if isinstance(self.capture.extras, dict) else {}
        return prov.get("producer") == "stircasadi.simulate" or bool(ex.get("@radiometric_unit", False))

    @property
    def colocated(self) -> bool:
        return bool(np.linalg.norm(self.source - self.camera) < 1e-9)

    @property
    def template(self) -> Template | None:
        return None if isinstance(self.irf, IdealIRF) else Template(self.irf, self.grid.bin_width)

    @property
    def frame(self) -> str:
        """``capture`` when the capture fixes the frame (known points or calibrated rays)."""
        return "capture" if (np.isfinite(self.known_xyz).all(axis=1).any()
                             or np.isfinite(self.rays).all(axis=1).any()) else "source-origin"

    def index(self, patch_id: int) -> int:
        hit = np.flatnonzero(self.ids == int(patch_id))
        if not hit.size:
            raise CaptureError(f"Unknown patch id {patch_id}; the capture's visible ids are "
                               f"{self.ids.tolist()[:20]}{' ...' if self.M > 20 else ''}.")
        return int(hit[0])

    def rows(self) -> np.ndarray:
        """Index (into ``ids``) of each STIR row."""
        return np.searchsorted(self.ids, self.ill)

    def cols(self) -> np.ndarray:
        return np.searchsorted(self.ids, self.obs)

    def noise_sigma(self) -> tuple[float, str]:
        """Noise std for whitening: the capture's (checked against the data by the caller) or
        estimated from the data."""
        if self.capture_sigma:
            return float(self.capture_sigma), "capture"
        tr, _ = self.capture.as_pairs()
        return noise_from_data(tr), "estimated from the data (first differences)"
