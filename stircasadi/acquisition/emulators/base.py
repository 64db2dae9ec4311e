"""The emulators' common parts: the fault model, the shared bench, and the base class that serves
one command line at a time on a pty or a loopback socket (see the package docstring)."""
from __future__ import annotations

import errno
import os
import select
import socket
import threading
import tty
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ...timegrid import TimeGrid

FAULT_KINDS = ("stall", "drop", "garbage", "truncate", "badlength", "disconnect")
TRANSPORTS = ("pty", "tcp")


@dataclass
class Fault:
    """One injected fault."""

    #: one of FAULT_KINDS
    kind: str
    #: the command (its start, e.g. 'HIST?', 'AIM', 'CURVE?') on which the fault fires
    command: str
    #: fire on the nth matching command (1-based)
    nth: int = 1
    #: seconds of silence for 'stall'
    stall_s: float = 1.0
    #: bytes dropped ('drop') or injected ('garbage')
    n_bytes: int = 8
    #: fire only once (a transient fault); False: on every match from the nth on
    once: bool = True

    def __post_init__(self):
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"Fault.kind must be one of {FAULT_KINDS}; got {self.kind!r}.")
        self.seen = 0
        self.fired = 0


class Bench:
    """What the emulated instruments share: the data source and the aimed patch."""

    def __init__(self, trace_for: Callable[[int], np.ndarray], n_patches: int, n_observed: int,
                 grid: TimeGrid):
        self.trace_for = trace_for
        self.n_patches = int(n_patches)
        self.n_observed = int(n_observed)
        self.grid = grid
        self.aimed: int | None = None
        self.lock = threading.Lock()

    def current(self) -> np.ndarray:
        with self.lock:
            i = self.aimed
        if i is None:
            return np.zeros((self.n_observed, self.grid.n_bins))
        row = np.asarray(self.trace_for(i), dtype=float)
        if row.shape != (self.n_observed, self.grid.n_bins):
            raise ValueError(f"trace_for({i}) must return shape {(self.n_observed, self.grid.n_bins)}; "
                             f"got {row.shape}")
        return row


class EmulatedDevice:
    """Base class: a thread that answers command lines on a pty (master side) or a loopback socket."""

    name = "device"

    def __init__(self, faults=(), terminator: bytes = b"\n", seed: int = 0, transport: str = "pty"):
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}; got {transport!r}.")
        self.transport = transport
        self.listener = self.conn = None
        self.faults = list(faults)
        self.term = terminator
        self.rng = np.random.default_rng(seed)
        self.log: list[str] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.master = self.slave = -1
        self.port = ""
        self.disconnected = False

    # ------------------------------------------------------------------ lifecycle
    def _open(self) -> None:
        if self.transport == "tcp":
            self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.listener.bind(("127.0.0.1", 0))          # loopback only, never the network
            self.listener.listen(1)
            self.listener.setblocking(False)
            self.port = f"TCPIP0::127.0.0.1::{self.listener.getsockname()[1]}::SOCKET"
        else:
            self.master, self.slave = os.openpty()
            tty.setraw(self.slave)
            os.set_blocking(self.master, False)
            self.port = os.ttyname(self.slave)
        self.disconnected = False

    def start(self) -> "EmulatedDevice":
        self._open()
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, name=f"emulator-{self.name}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        self._close_fds()

    def reconnect(self) -> str:
        """Plug the cable back in: a fresh pty (new path) served by a fresh thread."""
        self.stop()
        self.start()
        return self.port

    def _close_fds(self) -> None:
        for sock in (self.conn, self.listener):
            if sock is not None:
                try:
                    sock.close()
                except OSError:
                    pass
        self.conn = self.listener = None
        for fd in (self.master, self.slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = -1

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    # ------------------------------------------------------------------ I/O
    def _send(self, data: bytes) -> None:
        view = memoryview(data)
        out = self.conn if self.transport == "tcp" else self.master
        while view and not self._stop.is_set() and out is not None:
            try:
                _, w, _ = select.select([], [out], [], 0.05)
            except (OSError, ValueError):
                return
            if not w:
                continue
            try:
                n = out.send(view) if self.transport == "tcp" else os.write(self.master, view)
            except BlockingIOError:
                continue
            except OSError:
                return
            view = view[n:]

    def _receive(self) -> bytes | None:
        """Bytes that arrived (b"" when none yet); None when the link is gone for good."""
        if self.transport == "tcp":
            if self.listener is None:
                return None
            if self.conn is None:
                r, _, _ = select.select([self.listener], [], [], 0.02)
                if r:
                    self.conn, _ = self.listener.accept()
                    self.conn.setblocking(False)
                    self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                return b""
            r, _, _ = select.select([self.conn], [], [], 0.02)
            if not r:
                return b""
            try:
                chunk = self.conn.recv(65536)
            except BlockingIOError:
                return b""
            except OSError:
                chunk = b""
            if not chunk:  # the client closed: wait for the next one
                self.conn.close()
                self.conn = None
            return chunk
        r, _, _ = select.select([self.master], [], [], 0.02)
        if not r:
            return b""
        try:
            return os.read(self.master, 65536)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO: nobody holds the slave
            if exc.errno == errno.EIO:
                self._sleep(0.01)
                return b""
            return None

    def _sleep(self, s: float) -> None:
        self._stop.wait(s)

    def _loop(self) -> None:
        buf = b""
        while not self._stop.is_set():
            try:
                chunk = self._receive()
            except (OSError, ValueError):
                return
            if chunk is None:
                return
            buf += chunk
            while self.term in buf:
                line, buf = buf.split(self.term, 1)
                cmd = line.decode("ascii", "replace").strip()
                if not cmd:
                    continue
                self.log.append(cmd)
                for part in [p.strip().lstrip(":") for p in cmd.split(";") if p.strip()] if self.splits else [cmd]:
                    if not self._dispatch(part):
                        return

    splits = False  # SCPI devices split a line at ';'

    def _dispatch(self, cmd: str) -> bool:
        try:
            reply = self.handle(cmd)
        except Exception as exc:  # an emulator bug must not kill the thread silently
            reply = f"ERR 99 emulator: {type(exc).__name__}: {exc}".encode() + self.term
        fault = self._fault_for(cmd)
        if fault is not None:
            if fault.kind == "disconnect":
                self.disconnected = True
                self._close_fds()
                return False
            if reply is None:
                reply = b""
            if fault.kind == "stall":
                self._sleep(fault.stall_s)
            elif fault.kind == "drop":
                mid = len(reply) // 2
                reply = reply[:mid] + reply[mid + fault.n_bytes:]
            elif fault.kind == "garbage":
                junk = bytes(self.rng.integers(0x80, 0x100, fault.n_bytes, dtype=np.uint8))
                reply = junk + reply
            elif fault.kind == "truncate":
                reply = reply[:len(reply) // 2]
            elif fault.kind == "badlength" and b"#" in reply:
                reply = reply[:reply.index(b"#")] + b"#9099999999"
        if reply:
            self._send(reply)
        return True

    def _fault_for(self, cmd: str) -> Fault | None:
        for f in self.faults:
            if cmd.upper().startswith(f.command.upper()):
                f.seen += 1
                if f.seen >= f.nth and (not f.once or f.fired == 0):
                    f.fired += 1
                    return f
        return None

    def line(self, text: str) -> bytes:
        return text.encode("ascii") + self.term

    def handle(self, cmd: str) -> bytes | None:  # pragma: no cover - abstract
        raise NotImplementedError
