"""Applications on the measured STIR and on the estimate (issue 14): relighting, direct/global
separation, reflectance-based segmentation, material replacement, deconvolution of coded
illumination and LTI identification. One application, one module; this face only re-exports."""
from .belief import SceneBelief
from .deconvolve import Code, DeconvolveSettings, Deconvolution, amcw, deconvolve, mls, pulse
from .relight import Illumination, Relit, relight_capture, superpose
from .render import RenderSettings, Rendering, auto_grid, monte_carlo, render, steady_state
from .replace import Replacement, make_brdf, replace_material
from .segment import SegmentSettings, Segmentation, segment
from .separate import Separation, separate_bounces, separate_capture, separate_nayar, separate_onsets
from .sysid import FIRModel, identify_fir, validate
from .twin import estimate_from_scene

__all__ = ["SceneBelief", "Code", "DeconvolveSettings", "Deconvolution", "amcw", "deconvolve", "mls",
           "pulse", "Illumination", "Relit", "relight_capture", "superpose", "RenderSettings",
           "Rendering", "auto_grid", "monte_carlo", "render", "steady_state", "Replacement",
           "make_brdf", "replace_material", "SegmentSettings", "Segmentation", "segment",
           "Separation", "separate_bounces", "separate_capture", "separate_nayar", "separate_onsets",
           "FIRModel", "identify_fir", "validate", "estimate_from_scene"]
