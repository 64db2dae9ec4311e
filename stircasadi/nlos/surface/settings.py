"""Typed settings of the hidden-surface fit (analysis by synthesis)."""
from __future__ import annotations

from dataclasses import dataclass

from ...errors import ReconstructionError

__all__ = ["SurfaceSettings"]


@dataclass
class SurfaceSettings:
    """Settings of ``fit_surface``."""

    #: nodes per side of the depth map at the finest level
    n_nodes: int = 16
    #: coarse-to-fine levels; level k has n_nodes / 2^(levels-1-k) nodes per side (at least 4)
    levels: int = 2
    #: lateral extent (x0, x1, y0, y1) in the relay frame; None: the initialiser's mask
    #: bounding box grown by ``margin``
    extent: tuple | None = None
    #: growth of the initialiser's bounding box on each side, as a fraction of its size
    margin: float = 0.15
    #: fit the impulse response's Gaussian width (else it stays at ``sigma0``)
    fit_sigma: bool = True
    #: initial impulse-response std (metres of path); None: the relay's IRF, else 1.5 bins
    sigma0: float | None = None
    #: the relay's ``gain`` is absolute (a simulated or calibrated relay): albedo is bounded by
    #: 1 and reported as such; False: a global gain is set from the initialiser and the albedo is
    #: relative (its upper bound lifted)
    known_gain: bool = False
    #: smoothness prior on the depth map's Laplacian: "none" (default: the std maps are the
    #: data's own Fisher bounds), "auto" (weight by the discrepancy principle; the std are then
    #: posterior std that do not cover the prior's bias), or a fixed non-negative weight
    prior: str | float = "none"
    #: depth change allowed within one solve (metres); None: 3 bins of path
    z_slack: float | None = None
    #: "lm": bounded Levenberg-Marquardt with the exact Gauss-Newton matrix (default; 5-20
    #: iterations); "ipopt": IPOPT with a limited-memory Hessian (hundreds of iterations)
    solver: str = "lm"
    #: re-centred solves per level when depths reach the slack
    outer: int = 3
    #: iteration limit per solve (LM iterations, or IPOPT iterations)
    max_iter: int = 30
    #: IPOPT tolerance (relative to the scaled objective)
    tol: float = 1e-5
    #: noise std per bin (data units); None: the relay's sigma, Poisson for counts, else
    #: estimated from the data (MAD of first differences)
    noise_sigma: float | None = None
    #: (trace, node) pairs evaluated per chunk (memory bound)
    chunk_pairs: int = 200_000
    #: minimum significance (albedo / its std) of a node in the surface mask
    mask_z: float = 3.0

    def validate(self) -> "SurfaceSettings":
        if not (int(self.n_nodes) >= 3):
            raise ReconstructionError(f"n_nodes must be >= 3; got {self.n_nodes!r}.")
        if not (int(self.levels) >= 1):
            raise ReconstructionError(f"levels must be >= 1; got {self.levels!r}.")
        if self.extent is not None and (len(self.extent) != 4 or self.extent[0] >= self.extent[1]
                                        or self.extent[2] >= self.extent[3]):
            raise ReconstructionError(f"extent must be (x0, x1, y0, y1) with x0 < x1, y0 < y1; got {self.extent!r}.")
        if self.solver not in ("lm", "ipopt"):
            raise ReconstructionError(f"solver must be 'lm' or 'ipopt'; got {self.solver!r}.")
        if isinstance(self.prior, str):
            if self.prior not in ("auto", "none"):
                raise ReconstructionError(f"prior must be 'auto', 'none' or a weight >= 0; got {self.prior!r}.")
        elif not (float(self.prior) >= 0):
            raise ReconstructionError(f"prior weight must be >= 0; got {self.prior!r}.")
        for name in ("sigma0", "z_slack", "noise_sigma"):
            v = getattr(self, name)
            if v is not None and not (v > 0):
                raise ReconstructionError(f"{name} must be > 0 or None; got {v!r}.")
        if self.max_iter < 1 or self.outer < 1 or self.chunk_pairs < 1000:
            raise ReconstructionError("max_iter and outer must be >= 1 and chunk_pairs >= 1000.")
        return self

    @classmethod
    def from_options(cls, **options) -> "SurfaceSettings":
        known = set(cls.__dataclass_fields__)
        bad = sorted(set(options) - known)
        if bad:
            raise ReconstructionError(f"Unknown surface option(s) {bad}; known: {sorted(known)}.")
        return cls(**options).validate()
