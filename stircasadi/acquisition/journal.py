"""The capture journal: an append-only file of completed rows that no failure can make unreadable.

When to use: by ``session.acquire`` (``stircasadi acquire``) while a capture runs. Each completed
STIR row is appended as one self-checking record and fsync'ed before the scan controller aims at
the next patch, so a full disk, a kill (SIGKILL, SIGTERM, Ctrl-C) or a power cut at any instant
loses at most the row in flight. ``--resume`` reads the journal back, drops a torn last record
and measures only the rows that are missing; at the end the rows are assembled into the Capture
file (``capture.CaptureWriter``) and the journal is removed.

File layout (little-endian)::

    b"STIRJRN1"                                   magic, 8 bytes
    record*:  kind (4 bytes: b"HDR1" | b"ROW1" | b"RES1")  length u32  crc32(payload) u32  payload
    HDR1 payload: JSON (grid, ids, n_observed, shots, legs, noise, provenance), first record
    ROW1 payload: row u32, patch i64, galvo x, y f64, finished unix s f64, n_observed x n_bins f64
    RES1 payload: JSON of one resumption (date, rows done before, instrument)

A record is valid when its kind is known, its length fits in the file and its CRC-32 matches;
reading stops at the first invalid record (the torn tail of an interrupted append), which is
truncated away before appending again. A row appears at most once (resume never redoes a row).

The output is locked (``flock`` on ``<out>.lock``, holding the writer's pid) so that a second
process writing the same capture is refused with a clear message.

Neglects: a disk that silently corrupts data already fsync'ed (the CRC then stops the reading
at that record, and the rows after it are measured again on resume).
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CaptureError, OutputError

MAGIC = b"STIRJRN1"
_REC = struct.Struct("<4sII")
_ROW = struct.Struct("<Iqddd")
_KINDS = (b"HDR1", b"ROW1", b"RES1")
#: signals held back while a record is written, so an interruption never tears a record
_HELD = tuple(s for s in (getattr(signal, n, None) for n in ("SIGINT", "SIGTERM", "SIGHUP")) if s)


def journal_path(out) -> Path:
    """The journal of the capture ``out``: ``<out>.journal``."""
    out = Path(out)
    return out.with_name(out.name + ".journal")


def lock_path(out) -> Path:
    out = Path(out)
    return out.with_name(out.name + ".lock")


@dataclass
class Row:
    """One completed row of the journal."""

    row: int
    patch: int
    galvo_deg: tuple
    finished_unix_s: float
    data: np.ndarray
    crc32: int


@dataclass
class JournalState:
    """What a journal holds: its header, the rows by row index, the resumptions."""

    header: dict | None
    rows: dict = field(default_factory=dict)
    resumed: list = field(default_factory=list)
    #: bytes of valid records (the file is truncated here before appending again)
    valid_end: int = 0
    #: bytes after ``valid_end`` (a torn record from an interrupted append)
    torn_bytes: int = 0


def read_journal(path) -> JournalState:
    """Read every valid record of a journal (a missing or header-less journal has no header)."""
    path = Path(path)
    try:
        blob = path.read_bytes()
    except FileNotFoundError:
        raise CaptureError(f"no capture journal {path}.") from None
    except OSError as exc:
        raise CaptureError(f"cannot read the capture journal {path}: {exc}.") from exc
    st = JournalState(header=None)
    if not blob.startswith(MAGIC):
        if blob and not MAGIC.startswith(blob):
            raise CaptureError(f"{path} is not a stircasadi capture journal (it does not start with "
                               f"{MAGIC!r}); move it away or choose another --out.")
        st.torn_bytes = len(blob)
        return st
    pos = len(MAGIC)
    while pos + _REC.size <= len(blob):
        kind, n, crc = _REC.unpack_from(blob, pos)
        end = pos + _REC.size + n
        if kind not in _KINDS or end > len(blob):
            break
        payload = blob[pos + _REC.size:end]
        if zlib.crc32(payload) != crc:
            break
        if kind == b"HDR1":
            if st.header is not None:
                break
            st.header = json.loads(payload)
        elif st.header is None:
            break
        elif kind == b"ROW1":
            r, patch, gx, gy, t = _ROW.unpack_from(payload)
            shape = (int(st.header["n_observed"]), int(st.header["n_bins"]))
            data = np.frombuffer(payload, dtype="<f8", offset=_ROW.size)
            if data.size != shape[0] * shape[1] or r in st.rows:
                break
            st.rows[r] = Row(r, patch, (gx, gy), t, data.reshape(shape).astype(np.float64), crc)
        else:
            st.resumed.append(json.loads(payload))
        pos = end
    st.valid_end = pos if st.header is not None else len(MAGIC)
    st.torn_bytes = len(blob) - st.valid_end
    return st


def _record(kind: bytes, payload: bytes) -> bytes:
    return _REC.pack(kind, len(payload), zlib.crc32(payload)) + payload


def _fsync_dir(folder: Path) -> None:
    with contextlib.suppress(OSError):
        fd = os.open(str(folder) or ".", os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


class Journal:
    """An open journal for appending (use :meth:`create` or :meth:`reopen`)."""

    def __init__(self, path: Path, fd: int, state: JournalState):
        self.path, self.fd, self.state = path, fd, state

    @classmethod
    def create(cls, path, header: dict) -> "Journal":
        """A new journal holding ``header`` (durable before this returns)."""
        path = Path(path)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_APPEND, 0o644)
        j = cls(path, fd, JournalState(header=header))
        try:
            j._append(MAGIC + _record(b"HDR1", json.dumps(header, default=str).encode()))
        except BaseException:
            j.close()
            raise
        _fsync_dir(path.parent)
        return j

    @classmethod
    def reopen(cls, path) -> "Journal":
        """Open an existing journal for appending after its last valid record (a torn tail is cut)."""
        path = Path(path)
        state = read_journal(path)
        fd = os.open(path, os.O_WRONLY | os.O_APPEND)
        try:
            if state.torn_bytes:
                os.ftruncate(fd, state.valid_end)
                os.fsync(fd)
        except OSError as exc:
            os.close(fd)
            raise _disk_error(path, exc, len(state.rows)) from exc
        return cls(path, fd, state)

    def _append(self, data: bytes) -> None:
        """Write ``data`` at the end and fsync it, with interrupting signals held back."""
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(self.fd, view):]
            os.fsync(self.fd)
        except OSError as exc:
            raise _disk_error(self.path, exc, len(self.state.rows)) from exc
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    def append_row(self, r: int, patch: int, galvo_deg, finished_unix_s: float, data) -> Row:
        """Append one completed row; it is on disk (fsync'ed) when this returns."""
        data = np.ascontiguousarray(data, dtype="<f8")
        payload = _ROW.pack(int(r), int(patch), float(galvo_deg[0]), float(galvo_deg[1]),
                            float(finished_unix_s)) + data.tobytes()
        rec = _record(b"ROW1", payload)
        self._append(rec)
        row = Row(int(r), int(patch), tuple(galvo_deg), float(finished_unix_s),
                  data.astype(np.float64), zlib.crc32(payload))
        self.state.rows[int(r)] = row
        return row

    def append_resumed(self, info: dict) -> None:
        self._append(_record(b"RES1", json.dumps(info, default=str).encode()))
        self.state.resumed.append(info)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def _disk_error(path: Path, exc: OSError, n_rows: int) -> OutputError:
    return OutputError(f"could not write the capture journal {path}: {exc.strerror or exc} "
                       f"(disk full or a file-size limit?). The {n_rows} row(s) saved before are safe; "
                       "free some space, then resume.")


class OutputLock:
    """An exclusive lock on a capture's output (``<out>.lock`` holds the writer's pid)."""

    def __init__(self, out):
        self.out = Path(out)
        self.path = lock_path(out)
        self.fd = -1

    def acquire(self) -> "OutputLock":
        import fcntl

        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                pid = os.read(fd, 32).decode("ascii", "replace").strip() or "?"
            finally:
                os.close(fd)
            raise CaptureError(f"{self.out} is being captured by another process (pid {pid}); only "
                               "one process may write a capture. Wait for it to finish, or stop it "
                               f"(kill -TERM {pid}) and run again with --resume.") from None
        self.fd = fd
        try:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        except OSError as exc:
            self.release()
            raise OutputError(f"cannot write the lock file {self.path}: {exc.strerror or exc}. "
                              "Free disk space or choose another --out.") from exc
        return self

    def release(self) -> None:
        if self.fd >= 0:
            with contextlib.suppress(OSError):
                self.path.unlink()
            os.close(self.fd)
            self.fd = -1

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
