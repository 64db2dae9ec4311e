"""Helpers for test suites that compare estimates with known scenes (``stircasadi.testing``):
the seeded scene generator, the comparison of an estimate with a truth, and assertions on its
error bars and their coverage (the same measures ``stircasadi study`` records)."""
from .assertions import assert_coverage, assert_within_sigma, coverage_interval, nominal_coverage
from .compare import EXACT_TOL, Comparison, compare
from .scenes import GeneratedScene, generate

__all__ = ["GeneratedScene", "generate", "compare", "Comparison", "EXACT_TOL",
           "assert_within_sigma", "assert_coverage", "coverage_interval", "nominal_coverage"]
