"""Typed settings of the hidden-surface fit (analysis by synthesis)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from ...errors import ReconstructionError
from ..fieldtypes import check_field_types
from .stdmaps import CLAIMS

__all__ = ["SurfaceSettings"]


@dataclass
class SurfaceSettings:
    """Settings of ``fit_surface``."""

    #: nodes per side of the depth map at the finest level
    n_nodes: int = 16
    #: coarse-to-fine levels; level k has n_nodes / 2^(levels-1-k) nodes per side (at least 4);
    #: each level starts from the previous one's maps, bilinearly interpolated
    levels: int = 2
    #: lateral extent (x0, x1, y0, y1) in the relay frame; None: the initialiser's mask
    #: bounding box grown by ``margin``
    extent: tuple | None = None
    #: an initialiser column holds a surface when it is in the volume's mask or its albedo is at
    #: least this fraction of the largest (the support that sets the extent and the start)
    init_fraction: float = 0.25
    #: growth of the initialiser's bounding box on each side, as a fraction of its size
    margin: float = 0.15
    #: surface reflectance: "lambertian" or "retroreflective" (the return leg of a
    #: retroreflector has no 1/d^2 and no cosines; confocal scans only)
    brdf: str = "lambertian"
    #: sensor response shape: "gaussian", "emg" (a Gaussian with an exponential tail, mode at
    #: the path length: single-photon detectors) or "auto" (the relay's IRF when it is
    #: Gaussian, else "emg")
    response: str = "auto"
    #: "auto": on a rectified scan that holds the relay's own return at t = 0 (single-photon
    #: confocal scans), measure the response's slow tails and the background's decay on it
    #: (``direct.py``); "none": never
    direct: str = "auto"
    #: fit the response's width (and tail); else they stay at ``sigma0`` / ``tail0``
    fit_sigma: bool = True
    #: initial Gaussian std of the response (metres of path); None: the relay's IRF, else 1.5 bins
    sigma0: float | None = None
    #: initial exponential tail of an "emg" response (metres of path); None: 2 x sigma0
    tail0: float | None = None
    #: the relay's ``gain`` is absolute (a simulated or calibrated relay): albedo is bounded by
    #: 1 and reported as such; False: a global gain is set from the initialiser and the albedo is
    #: relative (its upper bound lifted)
    known_gain: bool = False
    #: smoothness prior on the depth map's Laplacian: "none" (default), "auto" (weight by the
    #: discrepancy principle), "gcv" (weight by generalised cross-validation, which needs no
    #: noise level: robust to a model mismatch that scales chi^2), or a fixed non-negative weight;
    #: what the std maps and the mask then rest on: ``claims_under_prior``
    prior: str | float = "none"
    #: under a prior (weight > 0): "data" (default) the std maps are the data's own Fisher bounds
    #: at the regularised solution, H^-1, which do not rely on the prior being true, and under the
    #: albedo's prior a mask node must hold evidence of its own in the data (``stdmaps.py``,
    #: ``mask.surface_mask``); "posterior": the posterior's (H + lam R)^-1, narrower, which do not
    #: hold the prior's bias (seeded study 1300-1323, prior "auto": 3 of 24 scenes SILENT-WRONG
    #: with them, none with "data"; none of the held-out 1400-1423 either), for a user who takes
    #: the prior as knowledge of the scene (then the edge nodes' albedo floor is 25 % of the
    #: bright albedo, ``mask.edge_std``). On a grid finer than the traces the data's std are wide
    #: where the prior alone determines a node (the 32 x 32 real chart over 16 x 16 traces:
    #: median depth std 23 mm against the posterior's 1.4 mm)
    claims_under_prior: str = "data"
    #: relative weight of the albedo's smoothness penalty (the integral of |grad rho|^2 over the
    #: extent) beside the depth's (the integral of (del^2 z)^2), both under the prior's weight;
    #: 0: the albedos are free (on grids finer than the traces they are then not determined);
    #: None (default): 1 where there is a prior (``prior`` not "none"), else 0 (``albedo_weight``)
    albedo_prior: float | None = None
    #: the cells the surface's edge may cut (``mask.cut_cells`` on the last level's solution)
    #: get a free in-plane centroid (the covered part's first moment, within the cell) and the
    #: last level is solved again with them; False: every cell emits from its node
    edge_offsets: bool = True
    #: with ``edge_offsets``: the cut cells' emitting parts also get a free extent per side about
    #: their centroids (``SurfaceModel(cell_extent=True)``), kept by their own ratio test
    #: (``cuts.py``); False: centroids only
    edge_extent: bool = True
    #: with ``edge_extent``: the emitting parts are parallelograms (a shear per cut cell beside its
    #: shrinks, ``SurfaceModel(cell_shear=True)``), tested with them; False: rectangles. Lowers
    #: chi2/dof on most low-noise twins but is not the default (``cuts.py``: seed 819)
    edge_shear: bool = False
    #: the edge nodes' std (``SurfaceResult.edge``: cells the surface's edge may cut and their
    #: neighbours) widened for the edge model's own error (``mask.edge_std``: floors in quadrature,
    #: 1 % of the cell pitch in depth, in albedo the larger of 5 % of the bright albedo (25 %
    #: under the albedo's prior with ``claims_under_prior="posterior"``) and the node's departure
    #: from its mask neighbours' mean; calibrated on the seeded study);
    #: False: the Fisher std of the noise alone, as for the other nodes
    edge_std_model: bool = True
    #: nodes whose albedo explains less of the data than noise would (``prune.py``: each node's
    #: chi^2 rise without it below the chi^2(2) quantile at p = 0.01) get albedo zero and the
    #: last level is solved again, kept by a likelihood-ratio test; False: every node stays free
    prune: bool = True
    #: two lit parts side by side with a depth step between them (``steps.py``) get separate
    #: height fields (no difference operator or prior crosses their border) and the last level is
    #: solved again, kept when it ends lower; False: one height field over the whole grid
    split_steps: bool = True
    #: after the last level's solves, one more sub-sample per cell side is asked whether it
    #: changes a lit node's solution (to first order) by half its std or more; if so the level is
    #: solved again with it, up to 4 (``quadrature.py``); False: the rule of ``subsamples`` alone
    quadrature_check: bool = True
    #: largest depth change of one solver step (metres); None: 1.5 x max(bin, sigma0)
    z_slack: float | None = None
    #: "lm": bounded Levenberg-Marquardt with the exact Gauss-Newton matrix (default; 5-20
    #: iterations); "ipopt": IPOPT with a limited-memory Hessian (hundreds of iterations)
    solver: str = "lm"
    #: iteration limit per level (LM iterations, or IPOPT iterations)
    max_iter: int = 30
    #: convergence: relative decrease of the objective below which LM stops (with tol_chi2 > 0
    #: once the undamped Gauss-Newton step confirms it, as below; IPOPT: its tol)
    tol: float = 1e-6
    #: LM also stops when a step lowered the whitened chi^2 (plus prior) by less than tol_chi2 x
    #: max(1, chi2/dof) and its quadratic model predicted no more: that step moved the unknowns
    #: by less than sqrt(tol_chi2) of their inflated std (jointly, in the Fisher metric); 0: off
    tol_chi2: float = 1.0
    #: noise std per bin (data units); None: the relay's sigma, Poisson for counts, else
    #: estimated from the data (MAD of first differences)
    noise_sigma: float | None = None
    #: q: each node's cell is integrated by q x q sub-samples (its delay spread otherwise enters
    #: as one moment-matched Gaussian, exact only for cells narrower than the response); None:
    #: the smallest q with a sub-cell side below 2 response sigmas, at most 2 (the cost grows as
    #: q^2), at the finest level (1 at the coarser levels, which only start the next one)
    subsamples: int | None = None
    #: memory of one chunk of Jacobian rows (MiB); the fit's peak memory is a few chunks plus
    #: the (2 nodes + 4)^2 Gauss-Newton matrix
    chunk_mb: float = 192.0
    #: threads over the trace chunks of the model's evaluations and Gauss-Newton products (the
    #: numbers do not depend on it); None: the CPUs this process may use, at most 4, or 1 where
    #: the environment sets OMP_NUM_THREADS=1 (one core per process, as the studies' workers run)
    threads: int | None = None
    #: precision of the Gauss-Newton products of the solver's steps ("float32" or "float64");
    #: the Fisher covariance is always accumulated from float64 products
    step_precision: str = "float32"
    #: minimum significance (albedo / its std) of a node in the surface mask: its own albedo's or
    #: its 3 x 3 neighbourhood's mean albedo's (std from the full covariance)
    mask_z: float = 3.0
    #: the explained-returns check (``explained.py``): the whitened residual over the relay's
    #: whole time range (after the gate) searched by a matched filter over ``explained_n``^3
    #: candidate points; a largest score above the noise level at false-alarm probability
    #: ``explained_p`` fails the fit ("unexplained returns"); False: not run
    explained: bool = True
    explained_p: float = 1e-3
    explained_n: int = 32

    def validate(self) -> "SurfaceSettings":
        check_field_types(self, "SurfaceSettings")
        if not (int(self.n_nodes) >= 3):
            raise ReconstructionError(f"n_nodes must be >= 3; got {self.n_nodes!r}.")
        if not (int(self.levels) >= 1):
            raise ReconstructionError(f"levels must be >= 1; got {self.levels!r}.")
        if self.extent is not None and (len(self.extent) != 4 or self.extent[0] >= self.extent[1]
                                        or self.extent[2] >= self.extent[3]):
            raise ReconstructionError(f"extent must be (x0, x1, y0, y1) with x0 < x1, y0 < y1; got {self.extent!r}.")
        if self.solver not in ("lm", "ipopt"):
            raise ReconstructionError(f"solver must be 'lm' or 'ipopt'; got {self.solver!r}.")
        if self.brdf not in ("lambertian", "retroreflective"):
            raise ReconstructionError(f"brdf must be 'lambertian' or 'retroreflective'; got {self.brdf!r}.")
        if self.response not in ("auto", "gaussian", "emg"):
            raise ReconstructionError(f"response must be 'auto', 'gaussian' or 'emg'; got {self.response!r}.")
        if self.direct not in ("auto", "none"):
            raise ReconstructionError(f"direct must be 'auto' or 'none'; got {self.direct!r}.")
        if not (0.0 < float(self.explained_p) < 1.0):
            raise ReconstructionError(f"explained_p must be in (0, 1); got {self.explained_p!r}.")
        if not (int(self.explained_n) >= 4):
            raise ReconstructionError(f"explained_n must be >= 4; got {self.explained_n!r}.")
        if self.step_precision not in ("float32", "float64"):
            raise ReconstructionError(f"step_precision must be 'float32' or 'float64'; got {self.step_precision!r}.")
        if isinstance(self.prior, str):
            if self.prior not in ("auto", "gcv", "none"):
                raise ReconstructionError(f"prior must be 'auto', 'gcv', 'none' or a weight >= 0; got {self.prior!r}.")
        elif not (float(self.prior) >= 0):
            raise ReconstructionError(f"prior weight must be >= 0; got {self.prior!r}.")
        if self.claims_under_prior not in CLAIMS:
            raise ReconstructionError(f"claims_under_prior must be one of {list(CLAIMS)} (what the std maps rest on "
                                      f"under a prior); got {self.claims_under_prior!r}.")
        if self.albedo_prior is not None:
            a = float(self.albedo_prior)            # a number: check_field_types
            if not (a >= 0 and math.isfinite(a)):
                raise ReconstructionError(f"albedo_prior must be a finite weight >= 0, or None (null) for the "
                                          f"default (1 under a prior, 0 without); got {self.albedo_prior!r}.")
        if self.edge_shear and not (self.edge_offsets and self.edge_extent):
            raise ReconstructionError("edge_shear leans the cut cells' shrunk emitting parts: it needs "
                                      "edge_offsets=True and edge_extent=True (or set edge_shear=False).")
        if self.albedo_weight() > 0 and self.prior == "none":
            raise ReconstructionError("albedo_prior weighs the albedo's penalty under the smoothness prior's "
                                      "weight: set prior='auto', 'gcv' or a weight as well (prior='none' has none).")
        for name in ("sigma0", "tail0", "z_slack", "noise_sigma"):
            v = getattr(self, name)
            if v is not None and not (v > 0):
                raise ReconstructionError(f"{name} must be > 0 or None; got {v!r}.")
        if self.subsamples is not None and not (1 <= int(self.subsamples) <= 8):
            raise ReconstructionError(f"subsamples must be within 1..8 or None; got {self.subsamples!r}.")
        if self.max_iter < 1 or not (self.chunk_mb >= 1):
            raise ReconstructionError(f"max_iter must be >= 1 and chunk_mb >= 1; got {self.max_iter!r}, "
                                      f"{self.chunk_mb!r}.")
        if self.threads is not None and not (1 <= int(self.threads) <= 64):
            raise ReconstructionError(f"threads must be within 1..64 or None; got {self.threads!r}.")
        if not (self.tol_chi2 >= 0):
            raise ReconstructionError(f"tol_chi2 must be >= 0; got {self.tol_chi2!r}.")
        if not (0 < self.init_fraction <= 1):
            raise ReconstructionError(f"init_fraction must be within (0, 1]; got {self.init_fraction!r}.")
        if not (0 <= self.margin <= 2):
            raise ReconstructionError(f"margin must be within [0, 2]; got {self.margin!r}.")
        return self

    def albedo_weight(self) -> float:
        """``albedo_prior``, or the default it stands for: 1 under a prior, 0 without one (a
        depth prior alone leaves the albedos of a grid finer than the traces undetermined: on the
        32 x 32 resolution chart 10 mask nodes, and a 90-degree turn of the wall's frame tilted
        the plane by 54 deg; with it 301 and 272 nodes, planes 0.4059 / 0.4062 m, 1.9 deg)."""
        if self.albedo_prior is not None:
            return float(self.albedo_prior)
        return 0.0 if self.prior == "none" else 1.0

    def n_threads(self) -> int:
        """``threads``, or the default it stands for (see the field)."""
        if self.threads is not None:
            return int(self.threads)
        import os

        from ..._cpus import usable_cpus
        if os.environ.get("OMP_NUM_THREADS", "").strip() == "1":
            return 1
        return min(4, usable_cpus())

    @classmethod
    def from_options(cls, **options) -> "SurfaceSettings":
        known = set(cls.__dataclass_fields__)
        bad = sorted(set(options) - known)
        if bad:
            raise ReconstructionError(f"Unknown surface option(s) {bad}; known: {sorted(known)}.")
        return cls(**options).validate()
