"""The .mat readers of the public relay-wall scans, re-exported from their importer modules.

Kept so that ``stircasadi.acquisition.nlos_mat.read_stanford_lct`` and friends keep working;
the readers live in ``stircasadi.acquisition.importers`` (one module per format) and ``detect``
is the registry's ``sniff`` (the format name of a file or folder, or None).
"""
from .importers.ccsocr import read_ccsocr
from .importers.general_nlos import read_general_nlos
from .importers.registry import sniff as detect
from .importers.stanford_lct import read_stanford_lct

__all__ = ["read_stanford_lct", "read_ccsocr", "read_general_nlos", "detect"]
