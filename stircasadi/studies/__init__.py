"""Studies: declarative sweeps of simulation and estimation (factors x repetitions), run on
Dask, cached per cell, tabulated with provenance and drawn (``stircasadi study``)."""
from .cache import CellCache, cell_key
from .cell import PeakMemory, build_setup, hard_verdict, run_cell
from .factors import FACTORS, SOLVERS, describe_factors
from .results import StudyResults, load_results
from .runner import BLAS_ENV, RunSettings, local_cluster, run_study
from .spec import MEASURES, Study, builtin_studies, load_study

__all__ = ["Study", "load_study", "builtin_studies", "MEASURES", "FACTORS", "SOLVERS",
           "describe_factors", "run_study", "RunSettings", "BLAS_ENV", "local_cluster", "run_cell",
           "build_setup", "hard_verdict", "PeakMemory", "cell_key", "CellCache", "StudyResults",
           "load_results"]
