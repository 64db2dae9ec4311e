"""Every exception class of stircasadi lives here (STYLE.md rule 4).

Messages say what was wrong, what is allowed, what was given and how to fix it.
"""
from __future__ import annotations


class StircasadiError(Exception):
    """Base class of all errors raised by stircasadi for bad input or failed work."""


class SceneError(StircasadiError, ValueError):
    """A scene or patch is malformed (zero area, non-unit normal, NaN position, unknown id...)."""


class TimeGridError(StircasadiError, ValueError):
    """A time grid is malformed or too short/late for the paths a simulation must record."""


class BRDFError(StircasadiError, ValueError):
    """BRDF parameters outside their physical range."""


class SensorError(StircasadiError, ValueError):
    """Impulse response or noise model malformed."""


class CaptureError(StircasadiError, ValueError):
    """A Capture (in memory or on disk) is malformed; the message names the field."""


class TransportError(StircasadiError, ValueError):
    """A forward-transport request that cannot be honoured as asked (method/scene mismatch)."""


class GeometryError(StircasadiError, ValueError):
    """The geometry stage cannot proceed (missing onsets, inconsistent distances...)."""


class ModelError(StircasadiError, ValueError):
    """A symbolic model is incomplete or used before/after setup()."""


class SolverError(StircasadiError, RuntimeError):
    """A numerical solve failed (IPOPT status, LM did not converge); never returned as a result."""

    def __init__(self, message: str, status: str | None = None, stats: dict | None = None):
        super().__init__(message)
        self.status = status
        self.stats = stats or {}


class InstrumentError(StircasadiError, RuntimeError):
    """An instrument misbehaved: stalled, sent garbage, disconnected. Names device, command, bytes."""


class ImportFormatError(CaptureError):
    """A file could not be imported in the named (or detected) format."""


class OutputError(StircasadiError, OSError):
    """An output path cannot be written (a folder, missing or read-only folder, equal to an input)."""


class IdentifiabilityWarning(UserWarning):
    """A parameter is not identifiable from the data (its Fisher information is ~0)."""


class PhysicsWarning(UserWarning):
    """The small-patch approximation is strained (form-factor row sum > 1, etc.)."""


class AcquisitionSettingsError(StircasadiError, ValueError):
    """An acquisition setting (port, baud rate, timeout, shots...) is outside its allowed range."""


class EstimateInputError(StircasadiError, ValueError):
    """An estimate.json cannot be rendered as asked (a null position or area, an UNRELIABLE
    verdict, a malformed covariance); the message names the patch, the value and the input
    that would fix it."""


class IlluminationError(StircasadiError, ValueError):
    """An illumination pattern does not fit the STIR or scene it is applied to (weights of the
    wrong length, unknown or unlit patch ids, delays or pulses that are not finite)."""


class CodeError(StircasadiError, ValueError):
    """An illumination code or input/output record cannot be deconvolved (ill-conditioned code,
    period shorter than the response, mismatched record lengths)."""


class ReconstructionError(StircasadiError, ValueError):
    """A relay-wall (NLOS) reconstruction cannot run on the given capture or settings."""


class StudyError(StircasadiError, ValueError):
    """A study spec is malformed (unknown factor, bad value, empty design) or its output folder
    cannot hold the results."""
