"""The time axis shared by every array: ``TimeGrid(start, bin_width, n_bins)``.

Time is optical path length in metres (t * c); t = 0 is the pulse's emission at the source.
Bin ``k`` covers the half-open interval ``[start + k*bin_width, start + (k+1)*bin_width)``.
Time is always the last axis of an array (DESIGN.md section 3).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .constants import C
from .errors import TimeGridError


@dataclass(frozen=True)
class TimeGrid:
    """A uniform time axis in metres of optical path.

    Parameters
    ----------
    start : float
        Left edge of bin 0, metres of path (may be negative or > 0 for rectified data).
    bin_width : float
        Width of one bin, metres of path (> 0). 1 cm is 33.36 ps.
    n_bins : int
        Number of bins (>= 1).
    """

    start: float
    bin_width: float
    n_bins: int

    def __post_init__(self) -> None:
        try:
            start = float(self.start)
            width = float(self.bin_width)
        except (TypeError, ValueError) as exc:
            raise TimeGridError(
                f"TimeGrid start and bin_width must be numbers in metres of path; got "
                f"start={self.start!r}, bin_width={self.bin_width!r}") from exc
        if not math.isfinite(start):
            raise TimeGridError(f"TimeGrid start must be finite metres of path; got {self.start!r}.")
        if not math.isfinite(width) or width <= 0:
            raise TimeGridError(
                f"bin_width must be > 0 metres of path; got {self.bin_width!r}. "
                "Did you pass picoseconds? Use TimeGrid.from_ps(start_ps, bin_width_ps, n_bins).")
        if width > 10.0:
            raise TimeGridError(
                f"bin_width={width} m of path is implausibly large (> 10 m = 33 ns). "
                "Did you pass picoseconds or bins? Use TimeGrid.from_ps(...) for picoseconds.")
        n = self.n_bins
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise TimeGridError(f"n_bins must be an integer >= 1; got {self.n_bins!r}.")
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "bin_width", width)
        object.__setattr__(self, "n_bins", int(n))

    # ---------------------------------------------------------------- constructors
    @classmethod
    def from_ps(cls, start_ps: float, bin_width_ps: float, n_bins: int) -> "TimeGrid":
        """Build a grid from picoseconds (converted once, here at the edge)."""
        if not bin_width_ps > 0:
            raise TimeGridError(f"bin_width_ps must be > 0 ps; got {bin_width_ps!r}.")
        return cls(start_ps * 1e-12 * C, bin_width_ps * 1e-12 * C, n_bins)

    # ---------------------------------------------------------------- derived axes
    @property
    def end(self) -> float:
        """Right edge of the last bin, metres of path."""
        return self.start + self.n_bins * self.bin_width

    @property
    def edges(self) -> np.ndarray:
        """The ``n_bins + 1`` bin edges, metres of path."""
        return self.start + self.bin_width * np.arange(self.n_bins + 1, dtype=float)

    @property
    def centres(self) -> np.ndarray:
        """The ``n_bins`` bin centres, metres of path."""
        return self.start + self.bin_width * (np.arange(self.n_bins, dtype=float) + 0.5)

    @property
    def bin_width_ps(self) -> float:
        """Bin width in picoseconds (for printing)."""
        return self.bin_width / C * 1e12

    def index(self, t: float | np.ndarray) -> np.ndarray:
        """Index of the bin holding path length ``t`` (may fall outside ``[0, n_bins)``)."""
        return np.floor((np.asarray(t, dtype=float) - self.start) / self.bin_width).astype(np.int64)

    def contains(self, t: float) -> bool:
        """Whether path length ``t`` falls inside the grid."""
        return self.start <= t < self.end

    def is_integer_aligned(self, tol: float = 1e-9) -> bool:
        """Whether ``start`` is a whole number of bins (needed by the integer-delay mode)."""
        r = self.start / self.bin_width
        return abs(r - round(r)) < tol

    def with_n_bins(self, n_bins: int) -> "TimeGrid":
        return TimeGrid(self.start, self.bin_width, n_bins)

    def __repr__(self) -> str:  # pragma: no cover - cosmetic
        return (f"TimeGrid(start={self.start:g} m, bin_width={self.bin_width:g} m "
                f"({self.bin_width_ps:.3g} ps), n_bins={self.n_bins})")
