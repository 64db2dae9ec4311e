"""The cell cache: one JSON file per finished cell, named by the hash of its parameters.

When to use
-----------
The runner asks ``CellCache.done(key)`` before submitting a cell and ``put`` as each result
arrives, so an interrupted study resumes where it stopped and a rerun skips what is done.

The key is ``sha256(canonical JSON of {params, package version, engine version})`` cut to 16
hex digits: the same parameters under the same package version give the same key on every
machine. A record is written atomically (``stircasadi.io``), so a kill never leaves half a file.

What it neglects
----------------
Code changes inside one package version do not change the key (the record keeps the commit it
was computed at, and ``stircasadi study --fresh`` ignores the cache).
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

from ..errors import StudyError
from ..io import atomic_write_text

__all__ = ["cell_key", "CellCache", "ENGINE_VERSION", "to_jsonable"]

#: bump when a record's meaning changes (new measures, other defaults)
ENGINE_VERSION = 1


def to_jsonable(o):
    """Plain JSON types from NumPy scalars/arrays; non-finite floats kept as strings
    ``"nan"``/``"inf"``/``"-inf"`` so the file stays strict JSON."""
    import numpy as np

    if isinstance(o, dict):
        return {str(k): to_jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [to_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return to_jsonable(o.tolist())
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, (float, np.floating)):
        f = float(o)
        return f if math.isfinite(f) else ("nan" if math.isnan(f) else ("inf" if f > 0 else "-inf"))
    return o


def from_jsonable(o):
    """Inverse of ``to_jsonable`` for the non-finite strings."""
    if isinstance(o, dict):
        return {k: from_jsonable(v) for k, v in o.items()}
    if isinstance(o, list):
        return [from_jsonable(v) for v in o]
    if o in ("nan", "inf", "-inf"):
        return float(o)
    return o


def cell_key(params: dict) -> str:
    """The cache key of a cell's parameters under this package version."""
    from .. import __version__

    doc = json.dumps({"params": to_jsonable(params), "version": __version__, "engine": ENGINE_VERSION},
                     sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(doc.encode()).hexdigest()[:16]


class CellCache:
    """``folder/<key>.json`` per finished cell."""

    def __init__(self, folder):
        self.folder = Path(folder)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise StudyError(f"Cannot create the study's cell folder {self.folder}: {exc}. Give an "
                             "--out folder you can write.") from exc

    def path(self, key: str) -> Path:
        return self.folder / f"{key}.json"

    def done(self, key: str) -> bool:
        return self.path(key).is_file()

    def get(self, key: str) -> dict | None:
        p = self.path(key)
        if not p.is_file():
            return None
        try:
            return from_jsonable(json.loads(p.read_text()))
        except (OSError, json.JSONDecodeError):
            return None   # unreadable: treated as not done, recomputed

    def put(self, key: str, record: dict) -> None:
        atomic_write_text(self.path(key), json.dumps(to_jsonable(record), separators=(",", ":")))

    def drop(self, key: str) -> None:
        self.path(key).unlink(missing_ok=True)
