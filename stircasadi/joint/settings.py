"""Settings of the joint estimator (geometry + reflectance + hidden patches): typed, validated.

Every field has a docstring (the attribute docstring below it); ``validate()`` raises a
``ModelError`` that names the field, the allowed values, what was given and the fix.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..errors import ModelError

_COSTS = ("oem", "pem")
_LIKELIHOODS = ("gaussian", "poisson")
_WEIGHTINGS = ("noise", "relative", "counts", "none")
_HESSIANS = ("exact", "gauss-newton", "limited-memory")
_LM_METHODS = ("lm", "trf")
_JACOBIANS = ("ad", "fd")


def _choice(name, value, allowed):
    if value not in allowed:
        raise ModelError(f"{name} must be one of {allowed}; got {value!r}.")


def _positive(name, value, allow_zero=False):
    ok = value >= 0 if allow_zero else value > 0
    if not isinstance(value, (int, float)) or not ok:
        raise ModelError(f"{name} must be a number {'>=' if allow_zero else '>'} 0; got {value!r}.")


@dataclass
class CostSettings:
    """What is minimised."""

    cost: str = "oem"
    """``"oem"``: output error (simulated STIR vs data). ``"pem"``: one-step prediction error
    with an AR(1) noise model y_k = M_k + e_k, e_k = a e_{k-1} + v_k estimated jointly (the
    innovations form of a deterministic transport model); it equals OEM when a = 0."""
    likelihood: str = "gaussian"
    """``"gaussian"`` (weighted least squares) or ``"poisson"`` (photon counts; needs the
    capture's Poisson ``scale``)."""
    weighting: str = "noise"
    """``"noise"``: residuals divided by the noise std (maximum likelihood; every bounce counts
    in proportion to its signal-to-noise ratio, and a noise-free capture falls back on
    ``sigma_floor_rel``). ``"relative"``: divided by sqrt(sigma^2 + (rel_weight * |y|)^2),
    which makes weak bounces count like strong ones. ``"counts"``: photon counts, divided by
    sqrt(max(s y, 1)) / s (s counts per STIR unit; Neyman's chi2, the Poisson variance from the
    data). ``"none"``: raw residuals."""
    sigma: float | None = None
    """Noise std in STIR units; None: from the capture's noise attributes, else estimated from
    the bins where the model deposits no light."""
    sigma_floor_rel: float = 1e-12
    """Lower bound on sigma, relative to the data's peak: about the resolution double precision
    leaves to sums of ~1e3 path terms. Real noise can sit 1e-10 below the peak (a third bounce
    at 1e-6 of the first with noise at 1e-4 of it), so the floor is below any noise a capture
    holds. Noise-free twins use it."""
    rel_weight: float = 1e-2
    """Relative error level of ``weighting="relative"``."""
    tikhonov: float = 0.0
    """lambda of the Tikhonov term lambda ||x - x_ref||^2 on the scaled unknowns (>= 0)."""
    fold: bool = True
    """Fold traces with fixed geometry into n_paths residuals by a per-trace QR (exact: same
    cost up to a constant, same Jacobian products; see ``ReflectanceNLP._folded_residual``).
    Gaussian OEM only; the solve then no longer grows with the number of bins."""
    gloss_prior: float = 1.0
    """Weight w of a weak prior w ||x_g - x_g0||^2 on the scaled Phong unknowns (specular: scale 1,
    exponent: scale 10) toward their initial values. It keeps the NLP well posed where the data
    do not see a patch's lobe (specular -> 0 leaves the exponent free); in chi^2 units it is
    negligible against any lobe the data do see. Identifiability flags ignore it (data-only
    Fisher information). 0 disables it."""
    weak_prior: bool = True
    """Add the weak prior 1/2 sum ((x - x0) / range)^2 (``uncertainty.PRIOR_RANGE``: albedo 1,
    position 1 m, tilt pi/2...): numbers the data do not identify stay at their start instead of
    wandering; its pull on identified numbers is below 1e-6 of their std."""
    tikhonov_reference: str = "zero"
    """``"zero"`` (lambda ||Theta||^2, scaled) or ``"initial"`` (shrink toward the initial guess)."""

    def validate(self) -> "CostSettings":
        _choice("cost", self.cost, _COSTS)
        _choice("likelihood", self.likelihood, _LIKELIHOODS)
        _choice("weighting", self.weighting, _WEIGHTINGS)
        _choice("tikhonov_reference", self.tikhonov_reference, ("zero", "initial"))
        if self.sigma is not None:
            _positive("sigma", self.sigma)
        _positive("sigma_floor_rel", self.sigma_floor_rel)
        _positive("rel_weight", self.rel_weight)
        _positive("tikhonov", self.tikhonov, allow_zero=True)
        _positive("gloss_prior", self.gloss_prior, allow_zero=True)
        if self.cost == "pem" and self.likelihood == "poisson":
            raise ModelError("cost='pem' models Gaussian AR(1) noise; it cannot be combined with "
                             "likelihood='poisson'. Use cost='oem' for photon counts.")
        return self


@dataclass
class ConstraintSettings:
    """Hard physical constraints (NLP constraints, never penalties)."""

    energy: bool = True
    """Per-patch BRDF energy: albedo + specular <= 1 for Phong patches (Lambertian: the bound
    albedo <= 1)."""
    stability: bool = True
    """Transport stability: every flux-transfer column sum sum_r rho_r F_{k->r} <= 1 - margin."""
    stability_margin: float = 1e-6
    """Margin below 1 of the stability constraint."""
    hidden_eps: float = 0.05
    """Half-width (metres) of the box that keeps a hidden position near its detected start
    (also the model's time window: larger boxes cost more)."""
    def validate(self) -> "ConstraintSettings":
        _positive("stability_margin", self.stability_margin, allow_zero=True)
        _positive("hidden_eps", self.hidden_eps)
        return self


@dataclass
class IpoptSettings:
    """IPOPT solve."""

    hessian: str = "exact"
    """``"exact"`` (CasADi AD), ``"gauss-newton"`` (J^T J plus exact constraint curvature) or
    ``"limited-memory"`` (L-BFGS, for comparison)."""
    tol: float = 1e-8
    """IPOPT ``tol``; with ``curvature_scaling`` it is in units of the unknowns' standard
    deviations (1e-8: every unknown converged to 1e-8 sigma)."""
    curvature_scaling: bool = True
    """Let IPOPT work on xi_j = d_j x_j, d_j = max(sqrt(F_jj(x0)), 1) (F: Gauss-Newton
    information), so strong and weak unknowns converge alike (the user-facing scaled x stays
    within 0.1-100); False: IPOPT's own gradient-based objective scaling."""
    max_iter: int = 200
    """IPOPT ``max_iter``."""
    acceptable_tol: float = 1e-3
    """IPOPT ``acceptable_tol`` (with ``acceptable_iter`` = 10): when strong and weak unknowns
    differ in curvature by ~1e15 (a first bounce vs a 1e-6 third bounce), round-off floors the
    dual infeasibility of the strong ones, and a large unexplained residual (returns of patches
    not yet modelled) floors the objective's precision; the solve then ends
    'Solved_To_Acceptable_Level' (every unknown within 1e-3 of its std of the optimum), reported as
    such."""
    print_level: int = 0
    """IPOPT ``print_level`` (0: quiet)."""
    raise_on_failure: bool = True
    """Raise ``SolverError`` when IPOPT does not converge (else return a result with
    ``success=False`` that every printer marks FAILED)."""
    extra: dict = field(default_factory=dict)
    """More IPOPT options, passed verbatim (``{"mu_strategy": "adaptive"}``)."""

    def validate(self) -> "IpoptSettings":
        _choice("hessian", self.hessian, _HESSIANS)
        _positive("tol", self.tol)
        if not isinstance(self.max_iter, int) or self.max_iter < 1:
            raise ModelError(f"max_iter must be an integer >= 1; got {self.max_iter!r}.")
        return self


@dataclass
class LMSettings:
    """Levenberg-Marquardt (scipy ``least_squares``)."""

    method: str = "lm"
    """``"lm"`` (MINPACK Levenberg-Marquardt, unbounded: bounds/constraints are checked after
    and a violation fails the solve) or ``"trf"`` (bounded trust region)."""
    jacobian: str = "ad"
    """``"ad"``: the CasADi Jacobian. ``"fd"``: scipy finite differences (the baseline)."""
    xtol: float = 1e-12
    ftol: float = 1e-12
    gtol: float = 1e-12
    max_nfev: int | None = None
    raise_on_failure: bool = True

    def validate(self) -> "LMSettings":
        _choice("method", self.method, _LM_METHODS)
        _choice("jacobian", self.jacobian, _JACOBIANS)
        for n in ("xtol", "ftol", "gtol"):
            _positive(n, getattr(self, n))
        return self


@dataclass
class UncertaintySettings:
    """Fisher-information uncertainty and identifiability flags."""

    compute: bool = True
    """Compute standard deviations and correlations at the optimum."""
    max_rel_std: float = 0.5
    """A BRDF parameter whose std exceeds this fraction of its allowed range (albedo: of 1) is
    flagged unidentifiable."""
    max_tilt_std_deg: float = 20.0
    """A normal rotation (``tilt``/``tilt2``) whose std exceeds this many degrees is unidentifiable."""
    max_position_std: float | None = None
    """A position std (metres) above this is flagged; None: the hidden eps."""
    null_tol: float = 1e-10
    """Eigenvalues of the correlation-normalised Fisher matrix D^-1/2 F D^-1/2 (diagonal 1) below
    null_tol span its null space (scale-free: strong and weak parameters are judged alike)."""
    chi2_inflate: bool = True
    """Scale every std by sqrt(chi2/dof) when the whitened residual exceeds its noise level
    (model mismatch shown, not hidden)."""
    chi2_max: float = 3.0
    """chi2/dof above this: the model does not explain the data; the estimate is UNRELIABLE."""

    def validate(self) -> "UncertaintySettings":
        _positive("max_rel_std", self.max_rel_std)
        _positive("max_tilt_std_deg", self.max_tilt_std_deg)
        _positive("null_tol", self.null_tol)
        if not self.chi2_max > 1:
            raise ModelError(f"chi2_max must be > 1; got {self.chi2_max!r}.")
        return self


@dataclass
class SearchSettings:
    """Residual-driven search for hidden patches (``stircasadi.joint.search``)."""

    enabled: bool = True
    """Search the residual for returns of patches not yet in the model."""
    max_hidden: int = 8
    """Most hidden patches added (``--hidden N`` fixes the number instead)."""
    p_value: float = 1e-6
    """A candidate is kept when its likelihood-ratio statistic (the drop of the whitened chi2)
    exceeds the chi2 quantile of 1 - p_value for the unknowns it adds."""
    grid_step_irf: float = 0.75
    """Search grid step in IRF widths (refined locally after the coarse maximum)."""
    max_traces: int = 600
    """Most traces the backprojection uses (the strongest residual ones when there are more)."""
    extended: bool = True
    """Model hidden patches as discs whose size the data may resolve (area unknown)."""

    def validate(self) -> "SearchSettings":
        _positive("p_value", self.p_value)
        _positive("grid_step_irf", self.grid_step_irf)
        if not isinstance(self.max_hidden, int) or self.max_hidden < 0:
            raise ModelError(f"max_hidden must be an integer >= 0; got {self.max_hidden!r}.")
        return self


@dataclass
class CheckSettings:
    """Self-checks of a solve against the data (``stircasadi.joint.checks``)."""

    trace_p: float = 1e-6
    """A trace fails when its whitened chi2 exceeds the 1 - trace_p / n_traces quantile."""
    unexplained_k: float = 6.0
    """A residual return above this many noise std of the matched filter is unexplained."""
    reciprocity_k: float = 6.0
    """Traces (i, j) and (j, i) disagree when their whitened difference exceeds this (rms x sqrt n)."""
    linearity_k: float = 4.0
    """Along an unknown's one-sigma direction the chi2 must rise within this factor of its
    linearised rise (``checks._linearity``)."""
    linearity_max_dirs: int = 300
    """At most this many unknowns' directions are probed (evenly spread over x)."""
    alternative_k: float = 10.0
    """The ``flat-alternative`` check fails when every height of a near-flat uncalibrated
    configuration is within this many of its std from zero (``checks._flat_alternative``)."""

    def validate(self) -> "CheckSettings":
        _positive("trace_p", self.trace_p)
        _positive("unexplained_k", self.unexplained_k)
        _positive("reciprocity_k", self.reciprocity_k)
        if not self.linearity_k > 1.0:
            raise ModelError(f"linearity_k must be > 1 (a factor); got {self.linearity_k!r}.")
        if not self.alternative_k > 0:
            raise ModelError(f"alternative_k must be > 0 (sigma); got {self.alternative_k!r}.")
        if int(self.linearity_max_dirs) < 1:
            raise ModelError(f"linearity_max_dirs must be >= 1; got {self.linearity_max_dirs!r}.")
        return self


@dataclass
class EstimateSettings:
    """All settings of the joint estimator (``stircasadi.pipeline.estimate_capture``)."""

    solver: str = "ipopt"
    """``"ipopt"`` or ``"lm"``."""
    bounces: int | None = None
    """Bounce order K of the model; None: 3 with hidden patches, else 2."""
    estimate_hidden_geometry: bool = True
    """Solve hidden positions jointly with the BRDF parameters (else fix them)."""
    free_positions_max: int = 40
    """Visible positions the capture does not give are refined by the joint fit when there are
    at most this many patches; above, they stay at the geometry stage's estimate and their
    covariance is propagated into the other unknowns (two-step, Murphy-Topel)."""
    time_limit: float | None = None
    """Wall-clock seconds for the whole estimate (``joint.budget``): solves stop at it and no
    stage starts past it; a fit it cut short is not reported (the estimate is the last converged
    one, flagged by the ``time-limit`` check). None: no limit."""
    cost: CostSettings = field(default_factory=CostSettings)
    constraints: ConstraintSettings = field(default_factory=ConstraintSettings)
    ipopt: IpoptSettings = field(default_factory=IpoptSettings)
    lm: LMSettings = field(default_factory=LMSettings)
    uncertainty: UncertaintySettings = field(default_factory=UncertaintySettings)
    search: SearchSettings = field(default_factory=SearchSettings)
    checks: CheckSettings = field(default_factory=CheckSettings)

    def validate(self) -> "EstimateSettings":
        _choice("solver", self.solver, ("ipopt", "lm"))
        if self.bounces is not None and (not isinstance(self.bounces, int) or self.bounces < 1):
            raise ModelError(f"bounces must be None or an integer >= 1; got {self.bounces!r}.")
        if self.time_limit is not None and not (isinstance(self.time_limit, (int, float))
                                                and np.isfinite(self.time_limit) and self.time_limit > 0):
            raise ModelError(f"time_limit must be None or a number of seconds > 0; got {self.time_limit!r}.")
        for f in fields(self):
            v = getattr(self, f.name)
            if hasattr(v, "validate"):
                v.validate()
        return self
