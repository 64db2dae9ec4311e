"""Physical constants and unit conversions used at the edges (DESIGN.md section 3)."""
from __future__ import annotations

#: speed of light in vacuum, m/s
C = 299_792_458.0


def ps_to_m(ps: float) -> float:
    """Picoseconds of time of flight to metres of optical path."""
    return ps * 1e-12 * C


def m_to_ps(m: float) -> float:
    """Metres of optical path to picoseconds."""
    return m / C * 1e12


def s_to_m(seconds: float) -> float:
    """Seconds to metres of optical path."""
    return seconds * C
