"""Capture sessions: step through the illumination patches; every completed row is durable at once.

When to use: ``stircasadi acquire`` and scripts that drive a real (or emulated) rig. For each
illumination patch ``i`` the session aims the scan controller, lets the detector average
(oscilloscope) or accumulate (counter) ``shots`` pulses, and appends ``stir[i, :, :]`` to the
capture journal (``journal``: one CRC-checked record, fsync'ed) *before* the next aim. A full
disk, a kill, Ctrl-C or a power cut therefore loses at most the row in flight, and the journal
always reads back. ``resume=True`` reopens the journal, checks that the rig still has the same
time axis, channels, patches and shots, and measures only the missing rows. When every row is in,
the rows are assembled into the Capture file with ``capture.CaptureWriter`` (atomic rename) and
the journal is removed; only a complete capture ever carries the final name.

The output is locked while a session runs; a second process is refused with a clear message.
Interrupting exceptions (``KeyboardInterrupt``, :class:`Interrupted` from SIGTERM, disk errors,
instrument faults) leave the session with ``exc.rows_safe``, ``exc.rows_total`` and
``exc.journal`` set, so the caller can say how many rows are safe and how to resume.

``provenance/`` records producer, date, instrument identities, the settings of every link,
shots, retries spent and the resume history; ``acquisition/`` holds, per row, the galvo angles
and the time it was finished.

Neglects: drift between an interrupted capture and its resumption (check ``provenance``).
"""
from __future__ import annotations

import datetime as _dt
import math
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np

from .. import __version__
from ..capture import Capture, CaptureWriter
from ..errors import AcquisitionSettingsError, CaptureError, InstrumentError, OutputError
from ..io import check_output
from ..progress import get_logger
from ..timegrid import TimeGrid
from .journal import Journal, OutputLock, journal_path, read_journal

log = get_logger(__name__)


class Interrupted(KeyboardInterrupt):
    """The capture was stopped by a signal (SIGTERM, SIGHUP); raised in the main thread."""

    def __init__(self, signame: str):
        super().__init__(signame)
        self.signame = signame


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def progress_printer(stream=None) -> Callable[[int, int, int, float], None]:
    """A progress callback printing ``patch 3 done, 3/10 (30 %), 1.2 s/patch, ETA 8 s`` lines."""
    stream = stream or sys.stderr

    def report(done: int, total: int, patch: int, elapsed: float) -> None:
        rate = elapsed / max(done, 1)
        eta = rate * (total - done)
        print(f"acquire: patch {patch} done, {done}/{total} ({100 * done / total:.0f} %), "
              f"{rate:.2f} s/patch, ETA {eta:.0f} s", file=stream, flush=True)
    return report


def _header(grid: TimeGrid, ids, n_obs: int, shots: int, detector, scan, legs_included: bool,
            extra_provenance: dict | None) -> dict:
    det = detector.describe()
    prov = {"producer": f"stircasadi {__version__} acquisition", "date": _now(),
            "instrument": f"{det.get('identity', '')} | scan: {scan.identity}",
            "detector": det, "scan_controller": scan.describe(), "shots": int(shots)}
    prov.update(extra_provenance or {})
    return {"start_m": grid.start, "bin_width_m": grid.bin_width, "n_bins": grid.n_bins,
            "illuminated_ids": [int(i) for i in ids], "n_observed": int(n_obs), "shots": int(shots),
            "legs_included": bool(legs_included), "detector": det.get("detector", ""),
            "noise": {"model": "poisson" if det.get("detector") == "counter" else "gaussian",
                      "shots": int(shots), "unit": det.get("unit", "")},
            "provenance": prov}


def _check_resumable(h: dict, path: Path, grid: TimeGrid, ids, n_obs: int, shots: int) -> None:
    problems = []
    if (h["n_observed"], h["n_bins"]) != (n_obs, grid.n_bins):
        problems.append(f"rows of {h['n_observed']} x {h['n_bins']} bins != rig's {n_obs} x {grid.n_bins}")
    if not math.isclose(float(h["bin_width_m"]), grid.bin_width, rel_tol=1e-9):
        problems.append(f"bin width {float(h['bin_width_m'])} m != rig's {grid.bin_width} m")
    if not math.isclose(float(h["start_m"]), grid.start, rel_tol=0, abs_tol=1e-6 * grid.bin_width):
        problems.append(f"start {float(h['start_m'])} m != rig's {grid.start} m")
    if int(h["shots"]) != int(shots):
        problems.append(f"shots {int(h['shots'])} != requested {shots}")
    if list(h["illuminated_ids"]) != [int(i) for i in ids]:
        problems.append("illuminated patch ids differ")
    if problems:
        raise CaptureError(f"cannot resume {path}: {'; '.join(problems)}. Resume with the same rig "
                           "settings, or start a new capture under another --out name.")


def _open_journal(out: Path, resume: bool, make_header: Callable[[], dict], ids, n_obs, shots,
                  grid, detector) -> Journal:
    jp = journal_path(out)
    if out.exists():
        extra = f" (its journal {jp} can be removed)" if jp.exists() else ""
        raise CaptureError(f"{out} already exists; choose another --out (a complete capture is "
                           f"never overwritten){extra}.")
    if jp.exists() and not resume:
        raise CaptureError(f"an interrupted capture is waiting in {jp}; pass --resume to complete "
                           "it, or delete it to start over.")
    if resume and not jp.exists():
        raise CaptureError(f"--resume given but there is no interrupted capture {jp}.")
    if resume:
        state = read_journal(jp)
        if state.header is not None:
            _check_resumable(state.header, jp, grid, ids, n_obs, shots)
            j = Journal.reopen(jp)
            if j.state.torn_bytes:
                log.info("acquire: dropped %d bytes of a torn last record (the row in flight)",
                         j.state.torn_bytes)
            j.append_resumed({"event": "resumed", "date": _now(), "done_before": len(j.state.rows),
                              "instrument": detector.identity})
            return j
        log.info("acquire: %s was interrupted before its header was written; starting afresh", jp)
    return Journal.create(jp, make_header())


def assemble(journal, out) -> Path:
    """Write the Capture ``out`` from a complete journal (``CaptureWriter``: atomic)."""
    st = read_journal(journal)
    h = st.header
    if h is None:
        raise CaptureError(f"{journal} holds no header; nothing to assemble.")
    ids = h["illuminated_ids"]
    missing = [ids[r] for r in range(len(ids)) if r not in st.rows]
    if missing:
        raise CaptureError(f"{journal}: patches {missing[:20]} are not measured yet; resume the capture.")
    n = len(ids)
    rows = [st.rows[r] for r in range(n)]
    prov = dict(h["provenance"])
    prov["resumed"] = [e for e in st.resumed if e.get("event") == "resumed"]
    prov["retries"] = int(sum(e.get("retries", 0) for e in st.resumed))
    prov["finished"] = _now()
    prov["journal_crc32"] = [int(r.crc32) for r in rows]
    grid = TimeGrid(h["start_m"], h["bin_width_m"], int(h["n_bins"]))
    acq = {"__attrs__": {"shots": int(h["shots"]), "detector": h["detector"], "complete": True},
           "acquired": np.ones(n, dtype=bool),
           "galvo_deg": np.array([r.galvo_deg for r in rows], dtype=float).reshape(n, 2),
           "finished_unix_s": np.array([r.finished_unix_s for r in rows])}
    with CaptureWriter(out, grid, n, int(h["n_observed"]), legs_included=h["legs_included"],
                       illuminated_ids=ids, observed_ids=np.arange(int(h["n_observed"])),
                       noise=dict(h["noise"]), provenance=prov, extras={"acquisition": acq}) as w:
        for r in rows:
            w.write_row(r.row, r.data)
        w.commit()
    return Path(out)


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
        Final Capture file; the rows go to ``<out>.journal`` until every patch is in.
    shots : int
        Pulses averaged (scope) or sync periods accumulated (counter) per patch.
    patches : sequence of int, optional
        Illumination patch ids in scan order (default: all of the controller's table).
    resume : bool
        Continue an interrupted capture from its journal.
    progress : callable(done, total, patch, elapsed_s), optional

    Returns
    -------
    Path of the complete capture. On any interruption the journal keeps every completed row
    and the exception carries ``rows_safe``, ``rows_total`` and ``journal``.
    """
    if isinstance(shots, bool) or not isinstance(shots, (int, np.integer)) or shots < 1:
        raise AcquisitionSettingsError(f"shots must be an integer >= 1 (pulses per patch); got {shots!r}.")
    out = check_output(out, what="capture")
    ids = list(range(scan.n_patches)) if patches is None else [int(p) for p in patches]
    if not ids or len(set(ids)) != len(ids) or min(ids) < 0 or max(ids) >= scan.n_patches:
        raise AcquisitionSettingsError(f"patches must be distinct ids in 0..{scan.n_patches - 1} "
                                       f"(the scan controller's table); got {patches!r}.")
    jp = journal_path(out)
    with OutputLock(out):
        grid = detector.grid()
        n_obs = detector.n_observed
        try:
            journal = _open_journal(out, resume, lambda: _header(grid, ids, n_obs, shots, detector,
                                                                 scan, legs_included, extra_provenance),
                                    ids, n_obs, shots, grid, detector)
        except (OutputError, KeyboardInterrupt) as exc:  # disk full or a signal while opening it
            if jp.exists():
                st = read_journal(jp)
                exc.rows_safe, exc.rows_total, exc.journal = len(st.rows), len(ids), jp
            raise
        log.info("acquire: journal %s (%d of %d rows already saved)", jp, len(journal.state.rows), len(ids))
        t0 = time.monotonic()
        try:
            todo = [r for r in range(len(ids)) if r not in journal.state.rows]
            total = len(ids)
            for r in todo:
                angles = scan.aim(ids[r])
                row = np.asarray(detector.acquire(shots), dtype=np.float64)
                if row.shape != (n_obs, grid.n_bins) or not np.all(np.isfinite(row)):
                    raise InstrumentError(f"{detector.port.device}: patch {ids[r]}: trace of shape "
                                          f"{row.shape} with {int(np.sum(~np.isfinite(row)))} non-finite "
                                          f"values; expected {(n_obs, grid.n_bins)} finite values.")
                saved = journal.append_row(r, ids[r], angles, time.time(), row)
                log.debug("acquire: saved row %d (patch %d) crc32 %08x", r, ids[r], saved.crc32)
                if progress is not None:
                    progress(len(journal.state.rows), total, ids[r], time.monotonic() - t0)
            retries = scan.port.retries_used + detector.port.retries_used
            if retries:
                journal.append_resumed({"event": "retries", "date": _now(), "retries": int(retries)})
            journal.close()
            assemble(jp, out)
        except BaseException as exc:
            journal.close()
            exc.rows_safe = len(journal.state.rows)
            exc.rows_total = len(ids)
            exc.journal = jp
            if isinstance(exc, InstrumentError) and exc.args:
                exc.args = (f"{exc.args[0]} -- capture interrupted: {exc.rows_safe} of {len(ids)} "
                            f"patches are saved in {jp}; reconnect and run again with --resume to "
                            "complete it.",)
            raise
        jp.unlink()
    Capture.read(out)  # the finished file must read back as a valid Capture
    return out


def read_partial(path: str | Path) -> Capture:
    """The rows measured so far in a capture journal (or ``out``'s journal), as a paired Capture."""
    path = Path(path)
    if path.suffix != ".journal":
        path = journal_path(path)
    st = read_journal(path)
    h = st.header
    if h is None or not st.rows:
        raise CaptureError(f"{path}: no row has been acquired yet.")
    grid = TimeGrid(h["start_m"], h["bin_width_m"], int(h["n_bins"]))
    ill = np.asarray(h["illuminated_ids"])
    rows = sorted(st.rows)
    traces = np.concatenate([st.rows[r].data for r in rows])
    obs = np.arange(int(h["n_observed"]))
    ii, jj = np.meshgrid(ill[rows], obs, indexing="ij")
    pairs = np.stack([ii.ravel(), jj.ravel()], axis=1)
    return Capture(grid=grid, traces=traces, pairs=pairs, legs_included=h["legs_included"],
                   noise=dict(h["noise"]), provenance=dict(h["provenance"], partial=True))
