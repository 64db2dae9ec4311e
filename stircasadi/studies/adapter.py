"""The one place where a study's solver factors meet the estimator.

When to use
-----------
``run_estimate(capture, params)`` is what every study cell calls to estimate: it maps the
solver factors (``solver``, ``tol``, ``max_iter``, ``time_limit``, ``model_bounces``) onto the
estimator's settings object and calls the public entry point ``stircasadi.pipeline.estimate_capture``.
When the estimator's settings change, only ``estimator_settings`` changes.

Mapping (onto ``stircasadi.joint.settings.EstimateSettings``, the estimator's settings):

=====================  =====================================================
factor                  setting
=====================  =====================================================
solver ipopt-exact      solver="ipopt", ipopt.hessian="exact"
solver ipopt-gauss-newton  solver="ipopt", ipopt.hessian="gauss-newton"
solver ipopt-lbfgs      solver="ipopt", ipopt.hessian="limited-memory"
solver lm-ad / lm-fd    solver="lm", lm.jacobian="ad" / "fd"
tol                     ipopt.tol; lm.xtol = lm.ftol = lm.gtol
max_iter                ipopt.max_iter; lm.max_nfev
time_limit              time_limit (seconds; 0: none)
model_bounces           bounces (the model's order; "auto": the estimator's choice)
=====================  =====================================================

A cell without solver factors passes ``settings=None`` (the estimator's defaults).

What it neglects
----------------
Whether the estimator honours the settings is read back from the result: ``settings_honoured``
is False when a stage names another solver family, True when the stages also name the
requested Hessian (IPOPT) or Jacobian (LM), None where the result does not tell.
"""
from __future__ import annotations

__all__ = ["estimator_settings", "run_estimate", "SOLVER_KEYS"]

SOLVER_KEYS = ("solver", "tol", "max_iter", "time_limit", "model_bounces")
_HESSIAN = {"ipopt-exact": "exact", "ipopt-gauss-newton": "gauss-newton", "ipopt-lbfgs": "limited-memory"}


def estimator_settings(params: dict):
    """The estimator's settings object for a cell's solver factors, or None for its defaults."""
    if not any(k in params for k in SOLVER_KEYS):
        return None
    from ..joint.settings import EstimateSettings

    s = EstimateSettings()
    solver = params.get("solver")
    if solver is not None:
        if solver.startswith("ipopt"):
            s.solver = "ipopt"
            s.ipopt.hessian = _HESSIAN[solver]
        else:
            s.solver = "lm"
            s.lm.jacobian = solver.split("-", 1)[1]
    if "tol" in params:
        s.ipopt.tol = float(params["tol"])
        s.lm.xtol = s.lm.ftol = s.lm.gtol = float(params["tol"])
    if "max_iter" in params:
        s.ipopt.max_iter = int(params["max_iter"])
        s.lm.max_nfev = int(params["max_iter"])
    if params.get("time_limit"):
        s.time_limit = float(params["time_limit"])
    if params.get("model_bounces", "auto") != "auto":
        s.bounces = int(params["model_bounces"])
    return s.validate()


def _solver_stages(result_json: dict) -> list[dict]:
    stages = result_json.get("stages") or {}
    items = stages.values() if isinstance(stages, dict) else stages
    return [st for st in items if isinstance(st, dict) and st.get("solver")]


def _honoured(params: dict, stages: list[dict]):
    """True / False where the result's stages say which solver (and Hessian / Jacobian) ran;
    None where they do not tell."""
    if not params.get("solver") or not stages:
        return None
    family, _, detail = params["solver"].partition("-")
    if not all(str(st["solver"]).startswith(family) for st in stages):
        return False
    key = "hessian" if family == "ipopt" else "jacobian"
    want = _HESSIAN.get(params["solver"], detail)
    told = [st.get(key) for st in stages if st.get(key) is not None]
    if not told:
        return None
    return all(str(t) == want for t in told)


def run_estimate(capture, params: dict):
    """Estimate ``capture`` (without its truth) with the cell's factors; returns
    (EstimateResult, info dict). ``params["declared_areas"]`` ({id: m^2}, set by the cell from
    the truth when the factor ``areas`` is ``"truth"``) is passed as the user's declared areas.

    ``info``: ``solver_reported`` (what the result's stages name), ``settings_honoured``.
    """
    from ..pipeline import estimate_capture

    settings = estimator_settings(params)
    hidden = params.get("hidden", "auto")
    areas = params.get("declared_areas")
    result = estimate_capture(capture, hidden=None if hidden == "auto" else int(hidden),
                              brdf=params.get("brdf", "lambertian"), areas=areas, settings=settings)
    stages = _solver_stages(result.to_json_dict())
    reported = sorted({str(st["solver"]) for st in stages})
    return result, {"solver_reported": ",".join(reported), "settings_honoured": _honoured(params, stages)}
