"""The factors a study may vary: one registry with the allowed values and what each one does.

When to use
-----------
``stircasadi.studies.spec`` validates every cell against ``FACTORS``; ``stircasadi study
--factors`` prints this table. A factor that is not set takes the problem's or scene's own
choice ("auto"), so a cell only departs from the scene where the study says so.

Forward factors go to ``stircasadi.transport.simulate`` and the ``Sensor``; solver factors go
to the estimator's settings through ``stircasadi.studies.adapter`` (the one place that knows the
estimator's settings object).
"""
from __future__ import annotations

import difflib
import numbers
from dataclasses import dataclass

from ..errors import StudyError

__all__ = ["Factor", "FACTORS", "SOLVERS", "EFFECTS", "check_factor", "describe_factors"]

#: solver names a study may give, mapped by the adapter onto the estimator's settings
SOLVERS = ("ipopt-exact", "ipopt-gauss-newton", "ipopt-lbfgs", "lm-ad", "lm-fd")
#: effects the ``effects`` study switches (``stircasadi.studies.effects``)
EFFECTS = ("none", "bounces", "occlusion", "glossy", "irf", "noise")


def _is_num(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _pos_num(v) -> bool:
    return _is_num(v) and v > 0


def _nonneg_num(v) -> bool:
    return _is_num(v) and v >= 0


def _pos_int(v) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool) and v >= 1


@dataclass(frozen=True)
class Factor:
    """One factor of a study."""

    name: str
    """The key in the spec."""
    doc: str
    """What it does, its unit and where it goes."""
    allowed: str
    """The allowed values, in words (printed in errors)."""
    check: object
    """A predicate on one value."""
    kind: str = "forward"
    """``"scene"``, ``"forward"``, ``"sensor"``, ``"estimate"`` or ``"study"``."""


FACTORS: dict[str, Factor] = {f.name: f for f in [
    Factor("problem", "a problem script: a name in stircasadi.problems or a path to a .py file",
           "a problem name or path", lambda v: isinstance(v, str) and v != "", "scene"),
    Factor("scene", "a scene generator 'module:function' (returns (scene, grid, sensor) or an object "
           "with .scene, .grid, .sensor) or a built-in 'hard:<name>' case (stircasadi.studies.hardcases)",
           "'module:function' or 'hard:<name>'", lambda v: isinstance(v, str) and ":" in v, "scene"),
    Factor("scene_args", "keyword arguments of the problem's build_scene or of the generator",
           "a table of keyword arguments", lambda v: isinstance(v, dict), "scene"),
    Factor("patches", "patch count, passed as n_patches to build_scene / the generator",
           "an integer >= 1", _pos_int, "scene"),
    Factor("noise", "Gaussian noise std relative to the STIR's peak, replacing the sensor's noise "
           "(0: none)", "a number >= 0", _nonneg_num, "sensor"),
    Factor("noise_model", "'sensor' (the problem's own), 'gaussian' (with `noise`), 'poisson' "
           "(with `photons`) or 'none'", "sensor | gaussian | poisson | none",
           lambda v: v in ("sensor", "gaussian", "poisson", "none"), "sensor"),
    Factor("photons", "expected counts in the brightest bin for noise_model='poisson'",
           "a number > 0", _pos_num, "sensor"),
    Factor("snr_db", "Gaussian noise at this peak signal-to-noise ratio in dB: "
           "sigma = peak * 10^(-snr_db / 20), peak = max of the ideal STIR", "a number",
           _is_num, "sensor"),
    Factor("irf", "impulse response: 'sensor' (the problem's), 'ideal', or a Gaussian FWHM in ps",
           "'sensor', 'ideal' or a number > 0 (ps)",
           lambda v: v in ("sensor", "ideal") or _pos_num(v), "sensor"),
    Factor("calibrated_camera", "'sensor' or a bool: the camera gives pixel rays and normals",
           "'sensor', true or false", lambda v: v == "sensor" or isinstance(v, bool), "sensor"),
    Factor("bin_width", "bin width in metres of path; the grid keeps its start and end",
           "a number > 0 (m)", _pos_num, "forward"),
    Factor("bin_scale", "multiplies the problem's bin width (0.5: twice as many bins); the grid "
           "keeps its start and end", "a number > 0", _pos_num, "forward"),
    Factor("n_bins", "number of bins at the grid's bin width (the end moves)", "an integer >= 1",
           _pos_int, "forward"),
    Factor("bounces", "bounce order of the simulation: 'auto' (what the scene needs), an integer "
           "or 'all'", "'auto', 'all' or an integer >= 1",
           lambda v: v in ("auto", "all") or _pos_int(v), "forward"),
    Factor("method", "simulation method of stircasadi.transport.simulate",
           "auto | bounces | frequency | statespace",
           lambda v: v in ("auto", "bounces", "frequency", "statespace"), "forward"),
    Factor("delay_mode", "'exact' path lengths or 'integer' (each leg rounded to bins)",
           "exact | integer", lambda v: v in ("exact", "integer"), "forward"),
    Factor("drop_direct", "observed ids whose traces lose their signal before noise (missing "
           "onsets): an id or a list of ids", "an integer or a list of integers",
           lambda v: _pos_int(v + 1) if isinstance(v, numbers.Integral) else
           (isinstance(v, list) and all(isinstance(x, numbers.Integral) and x >= 0 for x in v)), "forward"),
    Factor("effect", "the effect the cell forces (effects study)", " | ".join(EFFECTS),
           lambda v: v in EFFECTS, "forward"),
    Factor("effect_state", "'auto' (what simulate chooses), 'on' or 'off' for `effect`",
           "auto | on | off", lambda v: v in ("auto", "on", "off"), "forward"),
    Factor("solver", "the estimator's solver", " | ".join(SOLVERS), lambda v: v in SOLVERS, "estimate"),
    Factor("tol", "solver tolerance (IPOPT tol; LM xtol = ftol = gtol)", "a number > 0",
           _pos_num, "estimate"),
    Factor("max_iter", "solver iteration limit", "an integer >= 1", _pos_int, "estimate"),
    Factor("time_limit", "the estimator's wall-time limit in seconds (EstimateSettings.time_limit; "
           "0: none, the default of a study cell); a cut estimate is flagged 'time-limit'",
           "a number >= 0 (s)", _nonneg_num, "estimate"),
    Factor("model_bounces", "bounce order of the estimator's model: 'auto' or an integer",
           "'auto' or an integer >= 1", lambda v: v == "auto" or _pos_int(v), "estimate"),
    Factor("hidden", "number of hidden patches the estimator places: 'auto' (detect) or an integer",
           "'auto' or an integer >= 0", lambda v: v == "auto" or (_pos_int(v + 1) if
                                                                  isinstance(v, numbers.Integral) else False),
           "estimate"),
    Factor("brdf", "the BRDF the estimator fits", "lambertian | phong",
           lambda v: v in ("lambertian", "phong"), "estimate"),
    Factor("areas", "'none' (estimated or reported as albedo x area) or 'truth' (declared areas)",
           "none | truth", lambda v: v in ("none", "truth"), "estimate"),
    Factor("estimate", "run the estimator (false: simulation measures only)", "true or false",
           lambda v: isinstance(v, bool), "estimate"),
    Factor("label", "a free label shown in tables and pictures", "a string",
           lambda v: isinstance(v, str), "study"),
]}


def check_factor(name: str, value) -> None:
    """Raise ``StudyError`` when ``name`` is unknown or ``value`` is not allowed."""
    f = FACTORS.get(name)
    if f is None:
        near = difflib.get_close_matches(name, FACTORS, n=1)
        hint = f" Did you mean {near[0]!r}?" if near else ""
        raise StudyError(f"Unknown study factor {name!r}.{hint} Known factors: {', '.join(FACTORS)} "
                         "(`stircasadi study --factors` describes them).")
    try:
        ok = bool(f.check(value))
    except TypeError:
        ok = False
    if not ok:
        raise StudyError(f"Study factor {name!r} must be {f.allowed}; got {value!r}.")


def describe_factors() -> str:
    """The registry as a plain-text table."""
    width = max(len(n) for n in FACTORS)
    return "\n".join(f"{f.name:<{width}}  [{f.kind}] {f.doc} ({f.allowed})" for f in FACTORS.values())
