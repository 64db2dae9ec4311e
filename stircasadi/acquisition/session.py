"""Capture sessions: step through the illumination patches and write each trace as it arrives.

When to use: ``stircasadi acquire`` and scripts that drive a real (or emulated) rig. For each
illumination patch ``i`` the session aims the scan controller, lets the detector average
(oscilloscope) or accumulate (counter) ``shots`` pulses, writes ``stir[i, :, :]`` into the
Capture HDF5 file and flushes it, so a crash or an unplugged cable loses at most the trace in
flight.

On disk, while the capture runs, the file is ``<out>.partial``: a valid Capture layout
(DESIGN.md section 4) plus a group ``acquisition/`` whose dataset ``acquired`` (bool, one per
illumination patch) says which rows are real. Unacquired rows hold zeros, so the partial file
is never given the final name: only a complete capture is renamed to ``<out>``. Resuming
(``resume=True``) reopens the partial file, checks that the rig still has the same time axis,
channels and shots, and measures only the missing rows. :func:`read_partial` returns the rows
measured so far as a paired Capture (nothing invented for the rest).

``provenance/`` records producer, date, instrument identities, the settings of every link,
shots, retries spent and the resume history.

Neglects: drift between an interrupted capture and its resumption (check ``provenance``).
"""
from __future__ import annotations

import datetime as _dt
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..capture import FORMAT, VERSION, Capture
from ..errors import AcquisitionSettingsError, CaptureError, InstrumentError
from ..timegrid import TimeGrid


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def partial_path(out: str | Path) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".partial")


def progress_printer(stream=None) -> Callable[[int, int, int, float], None]:
    """A progress callback printing ``patch 3/10 (30 %), 1.2 s/patch, ETA 8 s`` lines."""
    stream = stream or sys.stderr

    def report(done: int, total: int, patch: int, elapsed: float) -> None:
        rate = elapsed / max(done, 1)
        eta = rate * (total - done)
        print(f"acquire: patch {patch} done, {done}/{total} ({100 * done / total:.0f} %), "
              f"{rate:.2f} s/patch, ETA {eta:.0f} s", file=stream, flush=True)
    return report


def _create(path: Path, grid: TimeGrid, ill_ids, n_obs: int, shots: int, detector, scan,
            legs_included: bool, extra_provenance: dict | None):
    import h5py

    n_ill = len(ill_ids)
    f = h5py.File(path, "w")
    f.attrs["format"] = FORMAT
    f.attrs["version"] = VERSION
    f.attrs["start_m"] = grid.start
    f.attrs["bin_width_m"] = grid.bin_width
    f.attrs["legs_included"] = bool(legs_included)
    f.create_dataset("stir", shape=(n_ill, n_obs, grid.n_bins), dtype="f8",
                     chunks=(1, n_obs, grid.n_bins), fillvalue=0.0)
    f.create_dataset("illuminated_ids", data=np.asarray(ill_ids, dtype=np.int64))
    f.create_dataset("observed_ids", data=np.arange(n_obs, dtype=np.int64))
    det = detector.describe()
    noise = f.create_group("noise")
    noise.attrs["model"] = "poisson" if det.get("detector") == "counter" else "gaussian"
    noise.attrs["shots"] = int(shots)
    noise.attrs["unit"] = det.get("unit", "")
    g = f.create_group("acquisition")
    g.create_dataset("acquired", data=np.zeros(n_ill, dtype=bool))
    g.create_dataset("galvo_deg", data=np.full((n_ill, 2), np.nan))
    g.create_dataset("finished_unix_s", data=np.full(n_ill, np.nan))
    g.attrs["shots"] = int(shots)
    g.attrs["detector"] = det.get("detector", "")
    g.attrs["complete"] = False
    prov = f.create_group("provenance")
    prov.attrs["producer"] = f"stircasadi {__version__} acquisition"
    prov.attrs["date"] = _now()
    prov.attrs["instrument"] = f"{det.get('identity', '')} | scan: {scan.identity}"
    prov.attrs["detector"] = json.dumps(det, default=str)
    prov.attrs["scan_controller"] = json.dumps(scan.describe(), default=str)
    prov.attrs["shots"] = int(shots)
    prov.attrs["resumed"] = json.dumps([])
    for k, v in (extra_provenance or {}).items():
        prov.attrs[k] = v if isinstance(v, (str, int, float, bool)) else json.dumps(v, default=str)
    f.flush()
    return f


def _check_resumable(f, path: Path, grid: TimeGrid, ill_ids, n_obs: int, shots: int) -> None:
    stir = f["stir"]
    want = (len(ill_ids), n_obs, grid.n_bins)
    problems = []
    if stir.shape != want:
        problems.append(f"stir shape {stir.shape} != rig's {want}")
    if not math.isclose(float(f.attrs["bin_width_m"]), grid.bin_width, rel_tol=1e-9):
        problems.append(f"bin width {float(f.attrs['bin_width_m'])} m != rig's {grid.bin_width} m")
    if not math.isclose(float(f.attrs["start_m"]), grid.start, rel_tol=0, abs_tol=1e-6 * grid.bin_width):
        problems.append(f"start {float(f.attrs['start_m'])} m != rig's {grid.start} m")
    if int(f["acquisition"].attrs["shots"]) != int(shots):
        problems.append(f"shots {int(f['acquisition'].attrs['shots'])} != requested {shots}")
    if not np.array_equal(f["illuminated_ids"][()], np.asarray(ill_ids)):
        problems.append("illuminated patch ids differ")
    if problems:
        raise CaptureError(f"cannot resume {path}: {'; '.join(problems)}. Resume with the same rig "
                           "settings, or start a new capture under another --out name.")


def acquire(scan, detector, out: str | Path, shots: int, patches=None, resume: bool = False,
            legs_included: bool = True, progress: Callable | None = None,
            extra_provenance: dict | None = None) -> Path:
    """Capture a STIR patch by patch into ``out`` (Capture HDF5 v1).

    Parameters
    ----------
    scan : ScanController
        Opened scan controller.
    detector : HistogramCounter or Oscilloscope
        Opened detector (``grid()``, ``acquire(shots)``, ``n_observed``, ``describe()``).
    out : path
        Final Capture file; written as ``<out>.partial`` until every patch is in.
    shots : int
        Pulses averaged (scope) or sync periods accumulated (counter) per patch.
    patches : sequence of int, optional
        Illumination patch ids in scan order (default: all of the controller's table).
    resume : bool
        Continue an interrupted capture in ``<out>.partial``.
    progress : callable(done, total, patch, elapsed_s), optional

    Returns
    -------
    Path of the complete capture. On an instrument fault the partial file keeps every
    completed trace and the exception says how to resume.
    """
    import h5py

    if isinstance(shots, bool) or not isinstance(shots, (int, np.integer)) or shots < 1:
        raise AcquisitionSettingsError(f"shots must be an integer >= 1; got {shots!r}.")
    out = Path(out)
    part = partial_path(out)
    if out.exists():
        raise CaptureError(f"{out} already exists; choose another --out (a complete capture is "
                           "never overwritten).")
    if part.exists() and not resume:
        raise CaptureError(f"an interrupted capture is waiting in {part}; pass --resume to complete "
                           "it, or delete it to start over.")
    if resume and not part.exists():
        raise CaptureError(f"--resume given but there is no interrupted capture {part}.")
    ids = list(range(scan.n_patches)) if patches is None else [int(p) for p in patches]
    if not ids or len(set(ids)) != len(ids) or min(ids) < 0 or max(ids) >= scan.n_patches:
        raise AcquisitionSettingsError(f"patches must be distinct ids in 0..{scan.n_patches - 1} "
                                       f"(the scan controller's table); got {patches!r}.")
    grid = detector.grid()
    n_obs = detector.n_observed
    if resume:
        f = h5py.File(part, "r+")
        try:
            _check_resumable(f, part, grid, ids, n_obs, shots)
        except Exception:
            f.close()
            raise
        hist = json.loads(f["provenance"].attrs.get("resumed", "[]"))
        hist.append({"date": _now(), "done_before": int(f["acquisition/acquired"][()].sum()),
                     "instrument": detector.identity})
        f["provenance"].attrs["resumed"] = json.dumps(hist)
        f.flush()
    else:
        f = _create(part, grid, ids, n_obs, shots, detector, scan, legs_included, extra_provenance)
    t0 = time.monotonic()
    try:
        acquired = f["acquisition/acquired"][()]
        todo = [r for r in range(len(ids)) if not acquired[r]]
        total, done = len(ids), int(acquired.sum())
        for r in todo:
            angles = scan.aim(ids[r])
            row = np.asarray(detector.acquire(shots), dtype=np.float64)
            if row.shape != (n_obs, grid.n_bins) or not np.all(np.isfinite(row)):
                raise InstrumentError(f"{detector.port.device}: patch {ids[r]}: trace of shape "
                                      f"{row.shape} with {int(np.sum(~np.isfinite(row)))} non-finite "
                                      f"values; expected {(n_obs, grid.n_bins)} finite values.")
            f["stir"][r] = row
            f["acquisition/galvo_deg"][r] = angles
            f["acquisition/finished_unix_s"][r] = time.time()
            f["acquisition/acquired"][r] = True
            f.flush()
            done += 1
            if progress is not None:
                progress(done, total, ids[r], time.monotonic() - t0)
        retries = scan.port.retries_used + detector.port.retries_used
        f["provenance"].attrs["retries"] = int(f["provenance"].attrs.get("retries", 0)) + retries
        f["acquisition"].attrs["complete"] = True
        f["provenance"].attrs["finished"] = _now()
        f.flush()
    except BaseException as exc:
        try:
            n_done = int(f["acquisition/acquired"][()].sum())
            f.flush()
        except Exception:  # pragma: no cover - file already unusable
            n_done = -1
        f.close()
        if isinstance(exc, (InstrumentError, KeyboardInterrupt)) and exc.args:
            exc.args = (f"{exc.args[0]} -- capture interrupted: {n_done} of {len(ids)} patches are "
                        f"saved in {part}; reconnect and run again with --resume to complete it.",)
        raise
    f.close()
    part.replace(out)
    Capture.read(out)  # the finished file must read back as a valid Capture
    return out


def read_partial(path: str | Path) -> Capture:
    """The traces measured so far in a ``.partial`` (or complete) capture, as a paired Capture."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise CaptureError(f"no such capture file: {path}.")
    with h5py.File(path, "r") as f:
        if "acquisition" not in f or "acquired" not in f["acquisition"]:
            raise CaptureError(f"{path} has no 'acquisition/acquired' mask; it was not written by "
                               "stircasadi acquire. Read it with Capture.read().")
        acq = f["acquisition/acquired"][()].astype(bool)
        stir = f["stir"][()]
        ill = f["illuminated_ids"][()]
        obs = f["observed_ids"][()]
        grid = TimeGrid(float(f.attrs["start_m"]), float(f.attrs["bin_width_m"]), stir.shape[-1])
        rows = np.flatnonzero(acq)
        traces = stir[rows].reshape(-1, grid.n_bins)
        ii, jj = np.meshgrid(ill[rows], obs, indexing="ij")
        pairs = np.stack([ii.ravel(), jj.ravel()], axis=1)
        prov = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f["provenance"].attrs.items()}
        legs = bool(f.attrs["legs_included"])
    if rows.size == 0:
        raise CaptureError(f"{path}: no trace has been acquired yet.")
    return Capture(grid=grid, traces=traces, pairs=pairs, legs_included=legs, provenance=prov)
