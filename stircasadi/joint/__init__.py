"""The joint estimator: geometry, reflectance and hidden patches in one CasADi NLP (IPOPT)."""
from .lm import solve_lm
from .nlp import JointNLP
from .result import JointEstimate, assemble
from .settings import (CheckSettings, ConstraintSettings, CostSettings, EstimateSettings,
                       IpoptSettings, LMSettings, SearchSettings, UncertaintySettings)
from .solve import Solution, ipopt, solve_nlp

__all__ = ["JointNLP", "JointEstimate", "assemble", "Solution", "ipopt", "solve_nlp", "solve_lm",
           "EstimateSettings", "CostSettings", "ConstraintSettings", "IpoptSettings", "LMSettings",
           "UncertaintySettings", "SearchSettings", "CheckSettings"]
