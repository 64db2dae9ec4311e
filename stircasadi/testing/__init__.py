"""Helpers for test suites that compare estimates with known scenes (``stircasadi.testing``):
the seeded scene generator (patches; hidden surfaces behind a relay wall), the comparison of an estimate with a truth, and assertions on its
error bars and their coverage (the same measures ``stircasadi study`` records)."""
from .assertions import assert_coverage, assert_within_sigma, coverage_interval, nominal_coverage
from .compare import EXACT_TOL, Comparison, compare
from .scenes import GeneratedScene, generate
from .surfaces import random_surface_twin, score_surface

__all__ = ["GeneratedScene", "generate", "random_surface_twin", "score_surface", "compare", "Comparison", "EXACT_TOL",
           "assert_within_sigma", "assert_coverage", "coverage_interval", "nominal_coverage"]
