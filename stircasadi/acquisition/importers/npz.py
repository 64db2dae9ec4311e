"""``npz``: NumPy archives.

Layout: ``stir`` (n_illuminated, n_observed, n_bins) or ``traces`` (n_pairs, n_bins) + ``pairs``;
the time axis as ``t`` (bin centres) or ``start`` + ``bin_width``, in ``time_unit`` (stored in the
archive or given); optional ``legs_included`` (a boolean).
"""
from __future__ import annotations

import numpy as np

from ...capture import Capture
from .registry import Format, register
from .validate import check_values, fail, grid as make_grid, make_capture, time_to_m, uniform_axis


def read_npz(path, time_unit: str | None = None, legs_included: bool | None = None) -> Capture:
    try:
        z = np.load(path, allow_pickle=False)
    except Exception as exc:
        raise fail(path, f"not a readable .npz archive ({type(exc).__name__}: {exc}).") from exc
    with z:
        keys = set(z.files)
        unit = str(z["time_unit"]) if "time_unit" in keys else time_unit
        if unit is None:
            raise fail(path, "the time unit is not stated: store 'time_unit' (s, ns, ps, m...) in the "
                              "archive or pass --time-unit.")
        if time_unit is not None and "time_unit" in keys and unit.lower() != time_unit.lower():
            raise fail(path, f"archive says time_unit={unit!r} but --time-unit {time_unit!r} was given.")
        if "stir" in keys:
            data = check_values(path, "stir", z["stir"])
            if data.ndim != 3:
                raise fail(path, f"'stir' must be (n_illuminated, n_observed, n_bins); got {data.shape}.")
            kw = {"stir": data}
        elif "traces" in keys and "pairs" in keys:
            data = check_values(path, "traces", z["traces"])
            kw = {"traces": data, "pairs": z["pairs"]}
        else:
            raise fail(path, f"archive must hold 'stir' or 'traces' + 'pairs'; found {sorted(keys)}.")
        n_bins = data.shape[-1]
        if "t" in keys:
            start, width = uniform_axis(path, time_to_m(z["t"], unit, path, "t"))
            if np.asarray(z["t"]).size != n_bins:
                raise fail(path, f"'t' has {np.asarray(z['t']).size} values but the data have {n_bins} bins.")
        elif "start" in keys and "bin_width" in keys:
            start = float(time_to_m(z["start"], unit, path, "start"))
            width = float(time_to_m(z["bin_width"], unit, path, "bin_width"))
        else:
            raise fail(path, "the time axis is missing: store 't' (bin centres) or 'start' and "
                              "'bin_width'.")
        legs = z["legs_included"] if "legs_included" in keys else \
            (True if legs_included is None else legs_included)
    return make_capture(path, "npz", grid=make_grid(path, start, width, n_bins), legs_included=legs,
                    provenance={"time_unit": unit}, **kw)


register(Format("npz", "NumPy .npz: stir or traces+pairs, t or start+bin_width, time_unit", read_npz,
                lambda p: p.suffix.lower() == ".npz"))
