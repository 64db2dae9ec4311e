"""Hidden surfaces by analysis by synthesis (depth map + albedo, CasADi + IPOPT). Re-exports."""
from .fit import fit_surface
from .grid import DepthGrid
from .result import SurfaceResult
from .settings import SurfaceSettings

__all__ = ["fit_surface", "DepthGrid", "SurfaceResult", "SurfaceSettings"]
