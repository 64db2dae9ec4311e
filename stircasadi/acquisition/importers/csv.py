"""``csv``: traces as text columns.

Layout: a header row; the first column ``time_<unit>`` (unit s, ns, ps, m, mm) or ``time`` with
``time_unit=`` given; values are bin centres, uniformly spaced. Other columns are traces named
``ill<i>_obs<j>`` (pair (i, j), ids >= 0, each pair once) or anything else (confocal (k, k)).
Lines starting with ``#`` are comments.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...capture import Capture
from .registry import Format, register
from .validate import check_values, fail, grid as make_grid, make_capture, time_to_m, uniform_axis


_PAIR = re.compile(r"^ill(-?\d+)_obs(-?\d+)$", re.IGNORECASE)


def _pairs_from_names(path, names: list[str]) -> np.ndarray:
    """Pairs named by the columns ``ill<i>_obs<j>``, or confocal (k, k) when no column is so named."""
    m = [_PAIR.match(n.strip()) for n in names]
    if not any(m):
        ids = np.arange(len(names))
        return np.stack([ids, ids], 1)
    if not all(m):
        odd = [n for n, x in zip(names, m) if not x][:5]
        raise fail(path, f"columns {odd} do not name a pair; when one column is named "
                         "ill<i>_obs<j>, every trace column must be.")
    pairs = np.array([[int(x.group(1)), int(x.group(2))] for x in m], dtype=np.int64)
    neg = [n for n, p in zip(names, pairs) if (p < 0).any()]
    if neg:
        raise fail(path, f"columns {neg[:5]} name negative patch ids; ids are integers >= 0.")
    seen: dict = {}
    for n, p in zip(names, map(tuple, pairs)):
        if p in seen:
            raise fail(path, f"columns {seen[p]!r} and {n!r} both name the pair (illuminated "
                             f"{p[0]}, observed {p[1]}); each pair may have one column.")
        seen[p] = n
    return pairs


def read_csv(path, time_unit: str | None = None, legs_included: bool = True) -> Capture:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise fail(path, f"cannot read as UTF-8 text ({exc}).") from exc
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if len(lines) < 3:
        raise fail(path, "a trace CSV needs a header row and >= 2 data rows.")
    header = [h.strip() for h in lines[0].split(",")]
    if len(header) < 2:
        raise fail(path, f"header must be 'time_<unit>,<trace>,...' with >= 1 trace column; got {lines[0]!r}.")
    m = re.match(r"^(?:t|time)(?:_(\w+)|\s*\[(\w+)\])?$", header[0], re.IGNORECASE)
    if not m:
        raise fail(path, f"first column must be the time axis named 'time_<unit>' (e.g. time_ps); "
                          f"got {header[0]!r}.")
    unit = m.group(1) or m.group(2) or time_unit
    if unit is None:
        raise fail(path, "the time unit is not stated: name the column time_ps/time_ns/time_s/time_m "
                          "or pass --time-unit.")
    if time_unit is not None and m.group(1 if m.group(1) else 2) and unit.lower() != time_unit.lower():
        raise fail(path, f"time unit in the header ({unit!r}) contradicts --time-unit {time_unit!r}.")
    rows = []
    for k, ln in enumerate(lines[1:], start=2):
        cells = ln.split(",")
        if len(cells) != len(header):
            raise fail(path, f"row {k} has {len(cells)} columns; the header has {len(header)}.")
        try:
            rows.append([float(c) for c in cells])
        except ValueError:
            raise fail(path, f"row {k} holds a non-number: {ln[:80]!r}.") from None
    a = np.array(rows)
    start, width = uniform_axis(path, time_to_m(a[:, 0], unit, path))
    traces = check_values(path, "traces", a[:, 1:].T)
    return make_capture(path, "csv", grid=make_grid(path, start, width, a.shape[0]), traces=traces,
                    pairs=_pairs_from_names(path, header[1:]), legs_included=legs_included,
                    provenance={"time_unit": unit, "columns": ",".join(header[1:])[:2000]})


register(Format("csv", "CSV: time_<unit> column + one column per trace", read_csv,
                lambda p: p.suffix.lower() == ".csv"))
