"""Where the real measured scans live: one configurable location for tests, notebooks, benchmarks.

``data_dir()`` is the folder of the measured NLOS scans (one sub-folder per dataset, each with a
NOTES.md). It is ``$STIRCASADI_DATA`` when set, else ``../shared/data`` beside the repository.
The data are read from there, never copied into the repository.
"""
from __future__ import annotations

import os
from pathlib import Path

from .errors import StircasadiError

__all__ = ["data_dir", "data_file", "ENV"]

ENV = "STIRCASADI_DATA"


def data_dir() -> Path:
    """The data folder (it may not exist on a machine without the scans)."""
    env = os.environ.get(ENV)
    if env:
        return Path(env).expanduser()
    return Path(__file__).resolve().parents[1].parent / "shared" / "data"


def data_file(*parts: str, required: bool = True) -> Path | None:
    """Path of a file under ``data_dir()``; a missing file raises (or returns None with
    ``required=False``) with a message saying where it was looked for and how to point there."""
    p = data_dir().joinpath(*parts)
    if p.exists():
        return p
    if not required:
        return None
    raise StircasadiError(f"Data file {p} not found. Set {ENV}=/path/to/data (the folder holding "
                          f"{parts[0] if parts else 'the datasets'}/) or place the scans at {data_dir()}.")
