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
    nodes where the data see a surface (albedo at least a tenth of the surface's bright albedo,
    ``mask.bright_nodes``, and significant at
    ``mask_z`` sigma on its own or as its 3 x 3 neighbourhood's mean) and the fit's
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
    #: (ny, nx) mask nodes at the surface's edge (a cell the edge may cut, or its neighbour;
    #: ``mask.edge_map``; None: no node marked, set in __post_init__)
    edge: np.ndarray | None = None
    #: the edge nodes' std are widened for the error of the edge's model (``mask.edge_std``,
    #: ``SurfaceSettings.edge_std_model``); False: they hold the noise only
    edge_widened: bool = False
    levels: list = field(default_factory=list)
    wall_time_s: float = 0.0
    reasons: list = field(default_factory=list)
    extras: dict = field(default_factory=dict)

    def __post_init__(self):
        if self.edge is None:       # a result built without one (tests, readers): no node marked
            self.edge = np.zeros(np.shape(self.mask), bool)

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

    def plane(self, weights: str = "precision") -> tuple[float, float]:
        """The plane through the mask's nodes (``nlos.volume.plane_fit``, in the grid's frame):
        its depth along ``w`` where it crosses the frame's axis (metres) and its tilt from ``w``
        (degrees). ``weights``: "precision" (1 / depth_std^2: the generalised least-squares plane
        of nodes with their stated error bars, so a node the data barely constrain counts
        little) or "albedo". On the Stanford 40 cm dot chart (12 x 12 nodes) the albedo-weighted
        plane tilts 10 deg, held by bright nodes between the rows of dots whose depths are
        2.5-7 cm off with a std of 0.8-2.5 mm; the precision-weighted one 2.4 deg, as f-k's.
        Raises ``ValueError`` with fewer than 3 mask nodes."""
        from ..volume import plane_fit

        m = self.mask
        if weights == "precision":
            wts = 1.0 / np.maximum(self.depth_std[m], 1e-12) ** 2
        elif weights == "albedo":
            wts = self.albedo[m]
        else:
            raise ValueError(f"weights must be 'precision' or 'albedo'; got {weights!r}.")
        yy, xx = np.meshgrid(self.grid.y, self.grid.x, indexing="ij")
        return plane_fit(np.stack([xx[m], yy[m], self.depth[m]], axis=1), wts)

    def summary(self) -> dict:
        m = self.mask
        return {"nodes": list(self.shape), "mask_nodes": int(m.sum()),
                "depth_median_m": float(np.median(self.depth[m])) if m.any() else None,
                "irf_fwhm_m": self.fwhm_irf, "response": self.response, "irf_sigma_m": self.sigma_irf,
                "irf_tail_m": self.tail, "brdf": self.brdf, "chi2_dof": self.chi2_dof,
                "prior_weight": self.prior_weight, "prior_method": self.prior_method,
                "success": self.success, "wall_time_s": self.wall_time_s}
