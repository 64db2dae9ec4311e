"""The ``stircasadi`` command line (entry point ``stircasadi.cli:main``); see ``cli.main``."""
from .commands import simulate_problem
from .commands import simulate_problem as _simulate_problem  # benchmarks/acquisition.py
from .main import build_parser, main

__all__ = ["main", "build_parser", "simulate_problem", "_simulate_problem"]
