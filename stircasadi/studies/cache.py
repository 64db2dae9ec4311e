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
from pathlib import Path

from ..errors import StudyError
from ..io import atomic_write_text
from ..report import json_default

__all__ = ["cell_key", "CellCache", "ENGINE_VERSION", "dumps"]

#: bump when a record's meaning changes (new measures, other defaults)
ENGINE_VERSION = 2


def dumps(o, **kw) -> str:
    return json.dumps(o, default=json_default, **kw)


def cell_key(params: dict) -> str:
    """The cache key of a cell's parameters under this package version."""
    from .. import __version__

    doc = dumps({"params": params, "version": __version__, "engine": ENGINE_VERSION},
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
            return json.loads(p.read_text())
        except (OSError, json.JSONDecodeError):
            return None   # unreadable: treated as not done, recomputed

    def put(self, key: str, record: dict) -> None:
        atomic_write_text(self.path(key), dumps(record, separators=(",", ":")))

    def keys(self) -> list[str]:
        """Keys of the finished records in the folder (sorted). A record being written is a
        hidden temporary file beside it (``.<key>.json.*``) and is not listed."""
        return sorted(p.stem for p in self.folder.glob("*.json")
                      if not p.name.startswith(".") and p.is_file())

    def drop(self, key: str) -> None:
        self.path(key).unlink(missing_ok=True)
