"""The inverse route, top to bottom: ``Capture -> GeometryEstimate -> model -> NLP -> Estimate``.

``estimate_capture(capture, ...)`` is what ``stircasadi estimate`` and ``stircasadi run`` call,
and what studies, applications and user scripts should call: it returns an ``EstimateResult``
whose ``to_json_dict()`` is the estimate.json structure documented in docs/estimate-json.md.
"""
from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["estimate_capture", "EstimateResult"]


@dataclass
class EstimateResult:
    """What the inverse route returns: the JSON structure and the objects behind it."""

    json: dict
    geometry: object = None
    joint: object = None
    extra: dict = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return bool(self.json.get("success", False))

    def to_json_dict(self) -> dict:
        return self.json


def estimate_capture(capture, hidden: int | None = None, brdf: str = "lambertian", areas=None,
                     settings=None) -> EstimateResult:
    """Estimate geometry and reflectance from ``capture`` (never reading its ``truth``)."""
    from .cli import _estimate

    geo, est, result = _estimate(capture, hidden, brdf)
    result = dict(result)
    result["version"] = 2
    result.setdefault("checks", [])
    result.setdefault("reasons", [])
    result["verdict"] = "OK" if result.get("success", False) else "UNRELIABLE"
    return EstimateResult(json=result, geometry=geo, joint=est)
