"""The one registry of file formats: readers (import), writers (export) and the one detector.

When to use: ``import_file(path)`` reads any registered format into a ``Capture`` (the format
detected when not given), ``export_file(capture, fmt, out)`` writes one, ``detect_format`` names
the format of a file or refuses it with the list of formats. A new format is one module that
calls :func:`register` (STYLE.md rule 17: one format, one converter, one registry line).

Detection asks every format's ``sniff(path) -> bool`` in registration order; a Capture file
(already ours) and a file no format claims are refused, naming the known formats.
"""
from __future__ import annotations

import inspect
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ...capture import FORMAT as CAPTURE_FORMAT
from ...capture import Capture
from ...errors import CaptureError, ImportFormatError
from ...progress import get_logger
from .validate import h5_keys

log = get_logger(__name__)


@dataclass
class Format:
    """One file format."""

    #: the name used by ``--format``
    name: str
    #: one line shown by ``stircasadi import --help``
    description: str
    #: ``reader(path, **options) -> Capture``
    reader: Callable
    #: ``sniff(path) -> bool``: whether a file (or folder) is in this format; never raises
    sniff: Callable[[Path], bool]
    #: ``writer(capture, path)`` for ``stircasadi export`` (None: import only)
    writer: Callable | None = None


#: format name -> Format, in detection order
FORMATS: dict[str, Format] = {}


def register(fmt: Format) -> Format:
    """Add a format to the registry (a format module calls this once)."""
    if fmt.name in FORMATS:
        raise ValueError(f"format {fmt.name!r} is registered twice")
    FORMATS[fmt.name] = fmt
    return fmt


def format_list() -> str:
    return ", ".join(FORMATS)


def exporters() -> list[str]:
    """Names of the formats that can be written."""
    return [k for k, f in FORMATS.items() if f.writer is not None]


def sniff(path) -> str | None:
    """The name of the format ``path`` is in, or None when no format claims it."""
    p = Path(path)
    for f in FORMATS.values():
        try:
            if f.sniff(p):
                return f.name
        except Exception:  # a sniffer never decides by crashing
            continue
    return None


def detect_format(path) -> str:
    """The format of ``path``; an unknown file is refused with the list of formats."""
    p = Path(path)
    if not p.exists():
        raise ImportFormatError(f"{p}: file not found.")
    if p.suffix.lower() in (".h5", ".hdf5", ".hdf"):
        info = h5_keys(p)
        if info is None:
            raise ImportFormatError(f"{p}: not a readable HDF5 file; known formats: {format_list()}.")
        if info[1].get("format") in (CAPTURE_FORMAT, CAPTURE_FORMAT.encode()):
            raise ImportFormatError(f"{p} is already a stircasadi Capture; use it directly (no "
                                    "import needed).")
    found = sniff(p)
    if found is None:
        raise ImportFormatError(f"{p}: the format is not recognised (extension "
                                f"{p.suffix.lower() or '(none)'!r}); known formats: {format_list()}. "
                                "Pass --format.")
    return found


def _options_for(fmt: Format, options: dict) -> dict:
    opts = {k: v for k, v in options.items() if v is not None}
    params = inspect.signature(fmt.reader).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return opts
    unused = [k for k in opts if k not in params]
    if unused:
        takes = [k for k in params if k != "path"]
        raise ImportFormatError(f"format {fmt.name!r} does not take option(s) {unused}; it takes "
                                f"{takes or 'none'}.")
    return opts


def import_file(path, fmt: str | None = None, **options) -> Capture:
    """Read ``path`` in format ``fmt`` (detected when None) and return a validated Capture."""
    if fmt is None:
        fmt = detect_format(path)
    if fmt not in FORMATS:
        raise ImportFormatError(f"unknown format {fmt!r}; allowed: {format_list()}.")
    if not Path(path).exists():
        raise ImportFormatError(f"{path}: file not found.")
    f = FORMATS[fmt]
    opts = _options_for(f, options)
    log.info("import: reading %s as %s", path, fmt)
    try:
        return f.reader(path, **opts)
    except (ImportFormatError, CaptureError):
        raise
    except (KeyError, ValueError, TypeError, IndexError, OSError) as exc:
        raise ImportFormatError(f"{path}: could not be read as {fmt!r} ({type(exc).__name__}: {exc}).") from exc


def export_file(capture: Capture, fmt: str, out, inputs=()) -> Path:
    """Write ``capture`` to ``out`` in format ``fmt`` (atomic: nothing at ``out`` changes on failure)."""
    from ...errors import OutputError
    from ...io import atomic_path, check_output

    if fmt not in FORMATS or FORMATS[fmt].writer is None:
        raise ImportFormatError(f"cannot export to {fmt!r}; formats that can be written: "
                                f"{', '.join(exporters()) or 'none'}.")
    out = check_output(out, inputs=inputs, what=fmt)
    try:
        with atomic_path(out) as tmp:
            FORMATS[fmt].writer(capture, tmp)
    except (OSError, RuntimeError) as exc:
        raise OutputError(f"Could not write {out}: {exc}. Nothing was changed at that path.") from exc
    log.info("export: wrote %s (%s)", out, fmt)
    return out
