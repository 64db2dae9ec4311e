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
    h = next((h for h in log.handlers if getattr(h, "_stircasadi", False)), None)
    if h is None:
        h = logging.StreamHandler(sys.stderr)
        h._stircasadi = True
        log.addHandler(h)
        log.propagate = False
    h.stream = sys.stderr  # the current standard error (it may have been redirected since)
    h.setFormatter(logging.Formatter("%(message)s" if level <= 0 else
                                     "%(asctime)s %(name)s %(levelname)s: %(message)s"))
    _state["bars"] = level >= 0 and (sys.stderr.isatty() or os.environ.get("STIRCASADI_PROGRESS", "") == "1")


def bars_enabled() -> bool:
    return bool(_state["bars"])


def progress(iterable=None, total: int | None = None, desc: str = "", unit: str = "it", **kw):
    """A tqdm progress bar (disabled when bars are off); use as an iterable wrapper or, with
    ``total``, as a context manager with ``.update(n)``. A bar appears only once its loop has run
    for ``delay`` seconds (default 1), so quick stages print nothing."""
    from tqdm import tqdm  # text bars on stderr (tqdm.auto warns in kernels without ipywidgets)

    kw.setdefault("delay", 1.0)
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not bars_enabled(),
                leave=False, file=sys.stderr, dynamic_ncols=True, **kw)
