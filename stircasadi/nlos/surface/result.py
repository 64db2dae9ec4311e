"""``SurfaceResult``: the fitted hidden surface with its Fisher error bars and its verdict."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .grid import DepthGrid

__all__ = ["SurfaceResult"]


@dataclass
class SurfaceResult:
    """Maps on ``grid`` (ny, nx): depth along the frame's w, albedo, unit normals (ny, nx, 3) facing
    the relay, their one-sigma Fisher std (inflated by sqrt(chi2/dof) when above 1), the mask of
    nodes where the data see a surface (albedo significant at ``mask_z`` sigma) and the fit's
    numbers: the response (kind, Gaussian width ``sigma_irf``, exponential ``tail`` of an emg,
    its FWHM), background, gain, prior weight and how it was chosen, the whitened residual
    chi2/dof, per-level solver status, the surface's ``brdf``."""

    grid: DepthGrid
    depth: np.ndarray
    albedo: np.ndarray
    normals: np.ndarray
    depth_std: np.ndarray
    albedo_std: np.ndarray
    normal_std: np.ndarray
    mask: np.ndarray
    sigma_irf: float
    sigma_irf_std: float | None
    background: float
    gain: float
    prior_weight: float
    prior_method: str
    chi2_dof: float
    dof: int
    albedo_relative: bool
    success: bool
    response: str = "gaussian"
    tail: float | None = None
    tail_std: float | None = None
    brdf: str = "lambertian"
    fwhm_irf: float = 0.0
    levels: list = field(default_factory=list)
    wall_time_s: float = 0.0
    reasons: list = field(default_factory=list)
    extras: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple:
        return self.depth.shape

    def points(self) -> np.ndarray:
        """(ny, nx, 3) node positions in the relay's (capture's) frame."""
        c, u, v, w = self.grid.frame
        return (self.grid.base_points() + self.depth.reshape(-1, 1) * w[None]).reshape(self.shape + (3,))

    def position_std(self) -> np.ndarray:
        """(ny, nx, 3): the depth std along the frame's w (lateral positions are the grid's)."""
        w = self.grid.frame[3]
        return np.abs(w)[None, None, :] * self.depth_std[..., None]

    def summary(self) -> dict:
        m = self.mask
        return {"nodes": list(self.shape), "mask_nodes": int(m.sum()),
                "depth_median_m": float(np.median(self.depth[m])) if m.any() else None,
                "irf_fwhm_m": self.fwhm_irf, "response": self.response, "irf_sigma_m": self.sigma_irf,
                "irf_tail_m": self.tail, "brdf": self.brdf, "chi2_dof": self.chi2_dof,
                "prior_weight": self.prior_weight, "prior_method": self.prior_method,
                "success": self.success, "wall_time_s": self.wall_time_s}
