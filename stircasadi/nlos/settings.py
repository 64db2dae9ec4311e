"""Typed settings of the volumetric reconstructions (LCT, f-k, backprojection)."""
from __future__ import annotations

from dataclasses import dataclass

from ..errors import ReconstructionError
from .fieldtypes import check_field_types

__all__ = ["VolumeSettings"]


@dataclass
class VolumeSettings:
    """Settings shared by ``lct``, ``fk`` and ``backprojection``."""

    #: sum this many time bins into one before reconstructing (4 ps x 4 = 16 ps, as the
    #: Stanford scripts do); 1 keeps the capture's bins
    bin_factor: int = 1
    #: zero every bin earlier than this path length (metres) to remove the wall's own return;
    #: None picks it from the data (past the summed histogram's early peak)
    gate_m: float | None = None
    #: keep only path lengths below this (metres) in the volume; None keeps the whole record. The
    #: surface fit (method "surface") models its own windows around the surface and its
    #: explained-returns check searches the whole record after the gate: a cut there ended the
    #: 32 x 32 chart's window inside its echo and tilted its plane 2.3 -> 6.6 deg (BENCHMARKS.md)
    t_max: float | None = None
    #: Lambertian (1/r^4) radiometric falloff; False = retroreflective (1/r^2)
    diffuse: bool = True
    #: LCT Wiener regularisation: the filter is conj(F) / (|F|^2 + 1 / snr)
    snr: float = 0.8
    #: floating-point precision of the FFTs and volumes: "float32" or "float64"
    dtype: str = "float32"
    #: backprojection: lateral voxels per side (None: the scan's own grid, else 32)
    n_lateral: int | None = None
    #: backprojection: lateral range (x0, x1, y0, y1) in the relay frame (metres along u, v from
    #: its centre); None: the relay points' extent (a hidden object beside the relay, e.g. a
    #: full STIR's hidden panel, lies outside it)
    xy_range: tuple | None = None
    #: backprojection: depth range (metres along the wall normal); None: from the time window
    z_range: tuple | None = None
    #: backprojection: depth voxels (None: one per half bin over z_range)
    n_depth: int | None = None
    #: backprojection: "none", "laplacian" (filtered backprojection, 3-D Laplacian of the volume)
    #: or "laplacian-z" (second derivative along depth only)
    bp_filter: str = "laplacian"
    #: backprojection: memory budget of one chunk of voxel x trace work, bytes
    chunk_bytes: int = 256 * 2 ** 20
    #: worker threads of the FFTs (scipy.fft); -1 = all cores
    workers: int = -1

    def validate(self) -> "VolumeSettings":
        check_field_types(self, "VolumeSettings")
        if not (isinstance(self.bin_factor, int) and self.bin_factor >= 1):
            raise ReconstructionError(f"bin_factor must be an integer >= 1; got {self.bin_factor!r}.")
        if self.gate_m is not None and not (self.gate_m >= 0):
            raise ReconstructionError(f"gate_m must be >= 0 metres of path or None; got {self.gate_m!r}.")
        if self.t_max is not None and not (self.t_max > 0):
            raise ReconstructionError(f"t_max must be > 0 metres of path or None; got {self.t_max!r}.")
        if not (self.snr > 0):
            raise ReconstructionError(f"snr must be > 0; got {self.snr!r}.")
        if self.dtype not in ("float32", "float64"):
            raise ReconstructionError(f"dtype must be 'float32' or 'float64'; got {self.dtype!r}.")
        if self.bp_filter not in ("none", "laplacian", "laplacian-z"):
            raise ReconstructionError(f"bp_filter must be 'none', 'laplacian' or 'laplacian-z'; got "
                                      f"{self.bp_filter!r}.")
        if self.n_lateral is not None and not (int(self.n_lateral) >= 2):
            raise ReconstructionError(f"n_lateral must be >= 2; got {self.n_lateral!r}.")
        if self.z_range is not None and not (len(self.z_range) == 2 and 0 <= self.z_range[0] < self.z_range[1]):
            raise ReconstructionError(f"z_range must be (z_min, z_max) with 0 <= z_min < z_max metres; "
                                      f"got {self.z_range!r}.")
        if self.xy_range is not None and not (len(self.xy_range) == 4 and self.xy_range[0] < self.xy_range[1]
                                              and self.xy_range[2] < self.xy_range[3]):
            raise ReconstructionError(f"xy_range must be (x0, x1, y0, y1) with x0 < x1, y0 < y1 metres; "
                                      f"got {self.xy_range!r}.")
        if self.chunk_bytes < 2 ** 20:
            raise ReconstructionError(f"chunk_bytes must be >= 1 MiB; got {self.chunk_bytes!r}.")
        return self

    @classmethod
    def from_options(cls, **options) -> "VolumeSettings":
        """Settings from keyword options; unknown names are refused with the list of known ones."""
        known = set(cls.__dataclass_fields__)
        bad = sorted(set(options) - known)
        if bad:
            raise ReconstructionError(f"Unknown volumetric option(s) {bad}; known: {sorted(known)}.")
        return cls(**options).validate()
