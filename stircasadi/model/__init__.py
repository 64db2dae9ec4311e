"""The symbolic transient model in CasADi (declare unknowns -> ``setup()`` -> solve elsewhere)."""
from .model import ModelInfo, TransientModel
from .output import OutputStructure
from .parameters import SPEC as PARAMETERS

__all__ = ["TransientModel", "ModelInfo", "OutputStructure", "PARAMETERS"]
