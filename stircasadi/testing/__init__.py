"""Test helpers for users' pytest suites: compare an estimate with a known truth, assert on its
error bars and their coverage (the same measures ``stircasadi study`` records)."""
from .assertions import assert_coverage, assert_within_sigma, coverage_interval, nominal_coverage
from .compare import EXACT_TOL, Comparison, compare, procrustes_about

__all__ = ["compare", "Comparison", "procrustes_about", "EXACT_TOL", "assert_within_sigma",
           "assert_coverage", "coverage_interval", "nominal_coverage"]
