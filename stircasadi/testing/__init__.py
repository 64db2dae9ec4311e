"""Helpers for test suites that compare estimates with known scenes (``stircasadi.testing``)."""
from .scenes import GeneratedScene, generate

__all__ = ["GeneratedScene", "generate"]
