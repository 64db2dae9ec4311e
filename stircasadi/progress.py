"""Logging and progress bars: one place for what the package tells its user while it works.

Every module logs through ``get_logger(__name__)`` (standard ``logging``, under the
``stircasadi`` logger) and wraps loops that can take more than a second or two in ``progress``
(a tqdm bar on standard error). ``set_verbosity`` (the CLI's ``-q``/``-v``) sets both: quiet shows
warnings only and no bars, verbose adds debug messages. Library users configure ``logging`` as
usual; bars are off unless a verbosity was set or ``STIRCASADI_PROGRESS=1``.
"""
from __future__ import annotations

import logging
import os
import sys

__all__ = ["get_logger", "set_verbosity", "progress", "bars_enabled"]

_ROOT = "stircasadi"
_state = {"bars": os.environ.get("STIRCASADI_PROGRESS", "") == "1"}


def get_logger(name: str = _ROOT) -> logging.Logger:
    """The package logger for module ``name`` (``stircasadi.*``)."""
    if not name.startswith(_ROOT):
        name = f"{_ROOT}.{name}"
    return logging.getLogger(name)


def set_verbosity(level: int = 0) -> None:
    """-1 quiet (warnings, no bars), 0 normal (info messages and bars on a terminal),
    1 verbose (debug messages)."""
    log = logging.getLogger(_ROOT)
    lvl = logging.WARNING if level < 0 else (logging.INFO if level == 0 else logging.DEBUG)
    log.setLevel(lvl)
    if not any(getattr(h, "_stircasadi", False) for h in log.handlers):
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(logging.Formatter("%(message)s" if level <= 0 else
                                         "%(asctime)s %(name)s %(levelname)s: %(message)s"))
        h._stircasadi = True
        log.addHandler(h)
        log.propagate = False
    _state["bars"] = level >= 0


def bars_enabled() -> bool:
    return bool(_state["bars"])


def progress(iterable=None, total: int | None = None, desc: str = "", unit: str = "it", **kw):
    """A tqdm progress bar (disabled when bars are off); use as an iterable wrapper or, with
    ``total``, as a context manager with ``.update(n)``."""
    from tqdm.auto import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not bars_enabled(),
                leave=False, file=sys.stderr, dynamic_ncols=True, **kw)
