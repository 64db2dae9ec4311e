"""Result and record files of the applications (HDF5 and JSON, written atomically).

``write_result`` / ``read_result``: one HDF5 file per application result: attributes
``format = "stircasadi.<app>"``, ``version = 1``, the grid (``start_m``, ``bin_width_m``) where
there is one, a JSON ``summary`` attribute, and one dataset per array.

The records file (``format = "stircasadi.records"``, version 1) holds coded-illumination
measurements for ``stircasadi deconvolve``:

    attrs   start_m, bin_width_m (the STIR's grid), n_bins (STIR length), periodic (bool),
            legs_included; optional noise_sigma
    records (n_codes, n_illuminated, n_observed, P)  the responses, on the STIR's grid
    codes   (n_codes, L_max) the emitted waveforms (energy per bin from t = 0), code_lengths
    illuminated_ids, observed_ids; optional irf (samples, peak at the centre)

Every write goes to a temporary file beside the target and is renamed over it
(``stircasadi.io.atomic_path``): an interrupted command never leaves a half file.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import CaptureError, CodeError
from ..io import atomic_path, atomic_write_text
from ..report import json_default
from ..timegrid import TimeGrid

__all__ = ["write_result", "read_result", "write_json", "write_records", "read_records"]


def _default(o):
    """``report.json_default``, and any other object as its text (what these files always wrote
    for the settings and metadata objects an application's summary may hold)."""
    try:
        return json_default(o)
    except TypeError:
        return str(o)


def write_json(path, obj) -> Path:
    """Write ``obj`` as indented JSON atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, default=_default))


def write_result(path, app: str, datasets: dict, summary: dict, grid: TimeGrid | None = None) -> Path:
    """One application result as HDF5 (module doc); None datasets are skipped."""
    import h5py

    path = Path(path)
    with atomic_path(path, suffix=".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = f"stircasadi.{app}"
            f.attrs["version"] = 1
            if grid is not None:
                f.attrs["start_m"] = grid.start
                f.attrs["bin_width_m"] = grid.bin_width
            f.attrs["summary"] = json.dumps(summary, default=_default)
            for k, v in datasets.items():
                if v is not None:
                    f.create_dataset(k, data=np.asarray(v))
    return path


def read_result(path) -> dict:
    """Read an application result: ``{"format", "summary", datasets..., "grid"}``."""
    import h5py

    with h5py.File(path, "r") as f:
        out = {k: f[k][()] for k in f}
        out["format"] = f.attrs["format"]
        out["summary"] = json.loads(f.attrs["summary"])
        if "start_m" in f.attrs:
            n = next((v.shape[-1] for k, v in out.items() if k in ("transient", "relit", "stir")), 1)
            out["grid"] = TimeGrid(float(f.attrs["start_m"]), float(f.attrs["bin_width_m"]), int(n))
    return out


def write_records(path, records, codes, grid: TimeGrid, ill_ids, obs_ids, irf=None,
                  noise_sigma: float | None = None, legs_included: bool = True) -> Path:
    """Write a records file (module doc); ``codes`` are ``deconvolve.Code`` objects."""
    import h5py

    records = np.asarray(records, float)
    L = max(c.length for c in codes)
    C = np.zeros((len(codes), L))
    for k, c in enumerate(codes):
        C[k, :c.length] = c.waveform
    path = Path(path)
    with atomic_path(path, suffix=".h5") as tmp:
        with h5py.File(tmp, "w") as f:
            f.attrs.update({"format": "stircasadi.records", "version": 1, "start_m": grid.start,
                            "bin_width_m": grid.bin_width, "n_bins": grid.n_bins,
                            "periodic": bool(codes[0].periodic), "legs_included": bool(legs_included)})
            if noise_sigma is not None:
                f.attrs["noise_sigma"] = float(noise_sigma)
            f.create_dataset("records", data=records)
            f.create_dataset("codes", data=C)
            f.create_dataset("code_lengths", data=np.array([c.length for c in codes]))
            f.create_dataset("code_names", data=np.array([c.name for c in codes], dtype="S"))
            f.create_dataset("illuminated_ids", data=np.asarray(ill_ids, int))
            f.create_dataset("observed_ids", data=np.asarray(obs_ids, int))
            if irf is not None:
                f.create_dataset("irf", data=np.asarray(irf, float))
    return path


def read_records(path) -> dict:
    """Read a records file; malformed files raise CaptureError naming the field."""
    import h5py

    from .deconvolve import Code

    path = Path(path)
    if not path.exists():
        raise CaptureError(f"Records file not found: {path}.")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise CaptureError(f"{path} is not a readable HDF5 file ({exc}); a records file has attribute "
                           "format='stircasadi.records'.") from exc
    with f:
        if f.attrs.get("format") != "stircasadi.records":
            raise CaptureError(f"{path}: attribute 'format' must be 'stircasadi.records'; got "
                               f"{f.attrs.get('format')!r}.")
        try:
            rec = f["records"][()]
            C = f["codes"][()]
            lens = f["code_lengths"][()]
            names = [n.decode() for n in f["code_names"][()]] if "code_names" in f else [""] * len(C)
            periodic = bool(f.attrs["periodic"])
            grid = TimeGrid(float(f.attrs["start_m"]), float(f.attrs["bin_width_m"]), int(f.attrs["n_bins"]))
            out = {"records": rec, "grid": grid,
                   "codes": [Code(C[k, :int(lens[k])], periodic, names[k]) for k in range(len(C))],
                   "illuminated_ids": f["illuminated_ids"][()], "observed_ids": f["observed_ids"][()],
                   "irf": f["irf"][()] if "irf" in f else None,
                   "noise_sigma": float(f.attrs["noise_sigma"]) if "noise_sigma" in f.attrs else None,
                   "legs_included": bool(f.attrs.get("legs_included", True))}
        except (KeyError, ValueError, TypeError) as exc:
            raise CaptureError(f"{path}: corrupted records file ({type(exc).__name__}: {exc}).") from exc
    if out["records"].ndim != 4 or out["records"].shape[0] != len(out["codes"]):
        raise CodeError(f"{path}: 'records' must be (n_codes={len(out['codes'])}, n_illuminated, "
                        f"n_observed, P); got {out['records'].shape}.")
    return out
