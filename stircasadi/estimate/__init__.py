"""Reflectance and joint hidden-geometry estimation (Algorithm 1, steps 2-4) on the symbolic model.

``estimate_reflectance(capture, geometry_estimate)`` is the pipeline; the parts are
``ReflectanceNLP`` (costs + constraints), ``solve_ipopt``, ``solve_lm``, ``fisher_uncertainty``,
``Estimate`` and the settings dataclasses.
"""
from __future__ import annotations

from .lm import solve_lm
from .nlp import ReflectanceNLP, solve_ipopt
from .result import Estimate
from .settings import (ConstraintSettings, CostSettings, EstimateSettings, IpoptSettings,
                       LMSettings, UncertaintySettings)
from .uncertainty import fisher_uncertainty

__all__ = ["ReflectanceNLP", "solve_ipopt", "solve_lm", "Estimate", "fisher_uncertainty",
           "EstimateSettings", "CostSettings", "ConstraintSettings", "IpoptSettings", "LMSettings",
           "UncertaintySettings", "estimate_reflectance", "report_table"]


def estimate_reflectance(capture, geometry_estimate=None, brdf: str = "lambertian", settings=None,
                         **kw):
    """Joint BRDF (+ hidden geometry) estimate from a Capture; see ``pipeline.estimate_reflectance``."""
    from .pipeline import estimate_reflectance as _impl

    return _impl(capture, geometry_estimate, brdf=brdf, settings=settings, **kw)


def report_table(estimate, truth=None, timings=None) -> str:
    """The table printed by ``stircasadi run``; see ``pipeline.report_table``."""
    from .pipeline import report_table as _impl

    return _impl(estimate, truth, timings=timings)
