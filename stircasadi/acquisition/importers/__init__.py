"""Importers and exporters: recordings in other formats into a ``Capture`` and back out.

One registry (``registry``: ``FORMATS``, ``detect_format``, ``import_file``, ``export_file``), one
set of validators (``validate``) and one module per format, each registering itself:

==============  =============================================================================
stanford-lct    confocal ``rect_data`` + ``width`` .mat (O'Toole et al. 2018)
ccsocr          ``sub_Sig`` + ``C_i``/``C_d`` .mat (CC-SOCR, f-k statue)
general-nlos    raw paired ``counts`` + ``setup.mat`` + peaks (general-NLOS 2024)
ytal            y-tal HDF5 (read and written: ``stircasadi export --format ytal``)
znlos           Zaragoza NLOS HDF5
ptu, phu        PicoQuant TCSPC recordings
csv, npz        text columns, NumPy archives
==============  =============================================================================

Every reader converts the time axis to metres of optical path at this edge and states whether
the times include the source and camera legs (``legs_included``).
"""
from . import stanford_lct, ccsocr, general_nlos, ytal, znlos, ptu, csv, npz  # noqa: F401  (register)
from .ccsocr import read_ccsocr
from .general_nlos import read_general_nlos
from .ptu import capture_from_histograms, phu_to_capture, read_phu, read_ptu
from .registry import (FORMATS, Format, detect_format, export_file, exporters, format_list,
                       import_file, register, sniff)
from .stanford_lct import read_stanford_lct
from .validate import TIME_UNITS, time_to_m
from .ytal import read_ytal, write_ytal
from .znlos import read_znlos

__all__ = ["FORMATS", "Format", "register", "detect_format", "sniff", "import_file", "export_file",
           "exporters", "format_list", "read_stanford_lct", "read_ccsocr", "read_general_nlos",
           "read_ytal", "write_ytal", "read_znlos", "read_ptu", "read_phu", "capture_from_histograms",
           "phu_to_capture", "TIME_UNITS", "time_to_m"]
