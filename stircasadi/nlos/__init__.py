"""Relay-wall (NLOS) reconstructions: LCT, f-k migration, backprojection and hidden surfaces.

Re-exports only; each algorithm lives in its own module.
"""
from .backprojection import backprojection
from .fk import fk
from .lct import lct
from .onset import OnsetDepths, onset_depths
from .relay import Relay, from_capture, from_stir
from .settings import VolumeSettings
from .volume import Maps, Volume, plane_fit

__all__ = ["lct", "fk", "backprojection", "Relay", "from_capture", "from_stir", "VolumeSettings",
           "Volume", "Maps", "plane_fit", "onset_depths", "OnsetDepths"]
from .estimate import METHODS, NLOSEstimate, estimate_capture
from .surface import SurfaceResult, SurfaceSettings, fit_surface

__all__ += ["estimate_capture", "NLOSEstimate", "METHODS", "fit_surface", "SurfaceSettings",
            "SurfaceResult"]
