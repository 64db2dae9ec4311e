"""Instrument emulators on pseudo-terminals and loopback sockets: links the drivers open like hardware.

When to use: tests, demos and dry runs of ``stircasadi acquire`` without a rig. Each emulator
serves one transport:

* ``transport="pty"``: a pty pair (``os.openpty``); the driver opens the slave path
  (``emulator.port``, e.g. ``/dev/pts/7``) through pyserial exactly as it would open
  ``/dev/ttyUSB0``;
* ``transport="tcp"``: a TCP socket on the loopback address only (127.0.0.1, an ephemeral port);
  ``emulator.port`` is the VISA resource ``TCPIP0::127.0.0.1::<port>::SOCKET`` that the drivers
  open through pyvisa, as they would a LAN instrument.

A thread answers with the wire protocol documented in ``scope``, ``scan`` and ``counter``.

Data come from a pluggable callable ``trace_for(i) -> (n_observed, n_bins)`` (the ideal STIR row
for aimed patch ``i``, e.g. the forward model's ``simulate(scene, grid).stir[i]``), shared through
a :class:`Bench` that also remembers where the scan controller aims:

* the counter returns ``Poisson(shots * (gain * trace + dark))`` counts (or, with
  ``pileup=True``, classic TCSPC first-photon histograms: a multinomial over bins with
  probabilities ``exp(-sum_{j<k} lam_j) (1 - exp(-lam_k))``, ``lam = gain * trace + dark``);
* the oscilloscope returns ``volts_per_unit * trace + N(0, noise_v)`` quantised to 16 bits.

Fault injection (:class:`Fault`, fired on the ``nth`` time a command starting with ``command``
arrives, once unless ``once=False``): ``stall`` (reply after ``stall_s``), ``drop`` (``n_bytes``
removed from the middle of the reply), ``garbage`` (``n_bytes`` of noise before the reply),
``truncate`` (only the first half of the reply is sent), ``badlength`` (a binary block's header
becomes ``#9099999999`` and nothing follows: a corrupt length field), ``disconnect`` (the port
hangs up: the pty or socket is closed, like an unplugged cable; :meth:`EmulatedDevice.reconnect`
plugs it back in on a new path). The scope emulator can also ignore ``DATA:SOURCE``
(``ignores_source=True``: always channel 1, as a misconfigured scope does) and send a DPO-style
preamble with extra fields (``dpo_preamble=True``).

Threads are daemons and :meth:`EmulatedDevice.stop` always joins them (use the emulators as context
managers); writes are non-blocking so a client that stops reading never hangs the emulator.

Neglects: baud-rate timing (a pty moves bytes as fast as it can).
"""
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

from ..constants import C, m_to_ps
from ..timegrid import TimeGrid
from .protocol import encode_block
from .scope import lecroy_encode, tek_preamble_text

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


class ScanControllerEmulator(EmulatedDevice):
    """The galvo controller: ``*IDN?``, ``NPATCH?``, ``TABLE``, ``AIM`` (see ``scan``)."""

    name = "scan controller"

    def __init__(self, bench: Bench, faults=(), settle_s: float = 0.0, seed: int = 0,
                 transport: str = "pty"):
        super().__init__(faults, seed=seed, transport=transport)
        self.bench = bench
        self.settle_s = settle_s
        # a default table: a small raster of angles
        self.table = {i: (0.5 * (i % 8), 0.5 * (i // 8)) for i in range(bench.n_patches)}

    def handle(self, cmd: str) -> bytes | None:
        toks = cmd.split()
        head = toks[0].upper()
        if head == "*IDN?":
            return self.line("STIRCASADI,GALVO-SCAN,EMU0001,1.0")
        if head == "NPATCH?":
            return self.line(f"NPATCH {len(self.table)}")
        if head == "TABLE" and len(toks) == 4:
            try:
                i, x, y = int(toks[1]), float(toks[2]), float(toks[3])
            except ValueError:
                return self.line("ERR 2 bad TABLE arguments")
            self.table[i] = (x, y)
            return self.line(f"OK TABLE {i}")
        if head == "AIM" and len(toks) == 2:
            try:
                i = int(toks[1])
            except ValueError:
                return self.line("ERR 2 bad patch index")
            if i not in self.table or i >= self.bench.n_patches:
                return self.line(f"ERR 1 patch {i} not in table")
            self._sleep(self.settle_s)
            with self.bench.lock:
                self.bench.aimed = i
            x, y = self.table[i]
            return self.line(f"OK AIM {i} {x:.6f} {y:.6f}")
        return self.line(f"ERR 0 unknown command {cmd[:40]}")


class CounterEmulator(EmulatedDevice):
    """A histogramming TCSPC counter (see ``counter`` for the protocol)."""

    name = "counter"

    def __init__(self, bench: Bench, gain: float = 1.0, dark: float = 0.0, sync_rate_hz: float = 1e7,
                 pileup: bool = False, faults=(), seed: int = 0, sync_offset_m: float = 0.0,
                 transport: str = "pty"):
        super().__init__(faults, seed=seed, transport=transport)
        self.bench = bench
        self.gain, self.dark, self.rate, self.pileup = gain, dark, sync_rate_hz, pileup
        self.sync_offset_m = sync_offset_m
        self.hist = np.zeros((bench.n_observed, bench.grid.n_bins), dtype=np.uint32)

    def _accumulate(self, n: int) -> None:
        lam = np.clip(self.gain * self.bench.current() + self.dark, 0, None)
        if not self.pileup:
            self.hist = self.rng.poisson(n * lam).astype(np.uint32)
            return
        out = np.empty_like(self.hist)
        for j in range(lam.shape[0]):
            surv = np.exp(-np.concatenate([[0.0], np.cumsum(lam[j])[:-1]]))
            p = surv * (1 - np.exp(-lam[j]))
            out[j] = self.rng.multinomial(n, np.append(p, max(0.0, 1 - p.sum())))[:-1]
        self.hist = out

    def handle(self, cmd: str) -> bytes | None:
        toks = cmd.split()
        head = toks[0].upper()
        g = self.bench.grid
        if head == "*IDN?":
            return self.line("PICOEMU,HISTO-8,EMU0002,2.1")
        if head == "HIST:NBIN?":
            return self.line(str(g.n_bins))
        if head == "HIST:RES?":
            return self.line(f"{g.bin_width_ps:.9g}")
        if head == "HIST:OFFS?":
            return self.line(f"{m_to_ps(g.start - self.sync_offset_m):.9g}")
        if head == "HIST:NCH?":
            return self.line(str(self.bench.n_observed))
        if head == "SYNC:RATE?":
            return self.line(f"{self.rate:.9g}")
        if head == "ACQ" and len(toks) == 2 and toks[1].isdigit():
            n = int(toks[1])
            self._sleep(n / self.rate)
            self._accumulate(n)
            return self.line(f"OK ACQ {n}")
        if head == "HIST?" and len(toks) == 2 and toks[1].isdigit():
            k = int(toks[1])
            if k >= self.hist.shape[0]:
                return self.line(f"ERR 1 no channel {k}")
            return encode_block(self.hist[k].astype("<u4").tobytes()) + self.term
        return self.line(f"ERR 0 unknown command {cmd[:40]}")


class ScopeEmulator(EmulatedDevice):
    """A sampling oscilloscope, Tektronix (``dialect='tektronix'``) or LeCroy (``'lecroy'``)."""

    name = "oscilloscope"
    splits = True

    def __init__(self, bench: Bench, dialect: str = "tektronix", volts_per_unit: float = 1.0,
                 noise_v: float = 0.0, full_scale_v: float | None = None, faults=(), seed: int = 0,
                 trigger_offset_m: float = 0.0, transport: str = "pty", ignores_source: bool = False,
                 dpo_preamble: bool = False):
        super().__init__(faults, seed=seed, transport=transport)
        #: a misconfigured scope: DATA:SOURCE is accepted but every waveform is channel 1's
        self.ignores_source = ignores_source
        #: DPO/MDO/MSO-style preamble with fields the driver does not use
        self.dpo_preamble = dpo_preamble
        self.bench = bench
        self.dialect = dialect
        self.vpu, self.noise_v = volts_per_unit, noise_v
        self.trigger_offset_m = trigger_offset_m
        self.full_scale_v = full_scale_v
        self.source = 1
        self.header = False

    def _raw(self, ch: int) -> tuple[np.ndarray, float]:
        row = self.bench.current()
        j = ch - 1
        v = self.vpu * (row[j] if 0 <= j < row.shape[0] else np.zeros(row.shape[1]))
        v = v + self.noise_v * self.rng.standard_normal(v.shape)
        if self.full_scale_v is None:  # auto-range once, on the largest return of any patch
            peak = max(float(np.max(np.abs(self.bench.trace_for(i)))) for i in range(self.bench.n_patches))
            self.full_scale_v = max(1e-6, 1.2 * abs(self.vpu) * peak + 4 * self.noise_v)
        ymult = self.full_scale_v / 32000.0
        raw = np.clip(np.round(v / ymult), -32768, 32767).astype(np.int16)
        return raw, ymult

    def handle(self, cmd: str) -> bytes | None:
        up = cmd.upper()
        g = self.bench.grid
        dt = g.bin_width / C
        t0 = (g.start - self.trigger_offset_m) / C + 0.5 * dt
        if up == "*IDN?":
            return self.line("TEKTRONIX,DSA8300-EMU,B000001,FV:1.0" if self.dialect == "tektronix"
                             else "LECROY,WAVEPRO-EMU,LCRY0001,9.0")
        if self.dialect == "tektronix":
            if up.startswith(("HEADER", "VERBOSE", "DATA:ENCDG", "DATA:WIDTH")):
                return None
            if up.startswith("DATA:SOURCE CH"):
                if not self.ignores_source:
                    self.source = int(up.rsplit("CH", 1)[1])
                return None
            if up == "DATA:SOURCE?":
                return self.line(f":DATA:SOURCE CH{self.source}")
            if up == "WFMOUTPRE?":
                self._pending = self._raw(self.source)
                raw, ymult = self._pending
                pre = {"BYT_NR": 2, "BIT_NR": 16, "ENCDG": "BIN", "BN_FMT": "RI", "BYT_OR": "MSB",
                       "NR_PT": raw.size, "WFID": f"Ch{self.source}, DC coupling, emulated", "PT_FMT": "Y",
                       "XUNIT": "s", "XINCR": dt, "XZERO": t0, "PT_OFF": 0, "YUNIT": "V",
                       "YMULT": ymult, "YOFF": 0.0, "YZERO": 0.0}
                if self.dpo_preamble:
                    pre.update({"PT_ORDER": "LINEAR", "DOMAIN": "TIME", "WFMTYPE": "ANALOG_YT",
                                "CENTERFREQUENCY": 0.0, "SPAN": 0.0, "REFLEVEL": 0.0})
                return self.line(tek_preamble_text(pre))
            if up == "CURVE?":
                raw, _ = getattr(self, "_pending", None) or self._raw(self.source)
                self._pending = None
                return b":CURVE " + encode_block(raw.astype(">i2").tobytes()) + self.term
            return None
        # LeCroy
        if up.startswith(("CHDR", "CFMT", "CORD")):
            return None
        if up.startswith("C") and ":WF?" in up:
            ch = 1 if self.ignores_source else int(up[1:up.index(":")])
            raw, ymult = self._raw(ch)
            return encode_block(lecroy_encode(raw, ymult, 0.0, dt, t0, source=ch - 1)) + self.term
        return None


class EmulatedRig:
    """A scan controller plus a detector emulator over one :class:`Bench` (context manager).

    Parameters
    ----------
    trace_for : callable
        ``trace_for(i) -> (n_observed, n_bins)`` ideal STIR row for patch ``i``.
    n_patches, n_observed : int
    grid : TimeGrid
        The instrument's time axis (metres of path).
    detector : {'counter', 'tektronix', 'lecroy'}
    scan_faults, detector_faults : list of Fault
    transport, scan_transport : {'pty', 'tcp'}
        The detector's and the scan controller's link (tcp: a loopback VISA socket resource).
    **detector_kw
        Passed to the detector emulator (``gain``, ``dark``, ``noise_v``, ``pileup``, ...).
    """

    def __init__(self, trace_for, n_patches: int, n_observed: int, grid: TimeGrid,
                 detector: str = "counter", scan_faults=(), detector_faults=(), seed: int = 0,
                 transport: str = "pty", scan_transport: str = "pty", **detector_kw):
        self.bench = Bench(trace_for, n_patches, n_observed, grid)
        self.scan = ScanControllerEmulator(self.bench, faults=scan_faults, seed=seed,
                                           transport=scan_transport)
        if detector == "counter":
            self.detector = CounterEmulator(self.bench, faults=detector_faults, seed=seed + 1,
                                            transport=transport, **detector_kw)
        elif detector in ("tektronix", "lecroy"):
            self.detector = ScopeEmulator(self.bench, dialect=detector, faults=detector_faults,
                                          seed=seed + 1, transport=transport, **detector_kw)
        else:
            raise ValueError(f"detector must be 'counter', 'tektronix' or 'lecroy'; got {detector!r}.")
        self.kind = detector

    def start(self) -> "EmulatedRig":
        self.scan.start()
        try:
            self.detector.start()
        except Exception:
            self.scan.stop()
            raise
        return self

    def stop(self) -> None:
        self.scan.stop()
        self.detector.stop()

    def reconnect(self) -> None:
        """Re-plug both cables (new pty paths in ``scan.port`` / ``detector.port``)."""
        self.scan.reconnect()
        self.detector.reconnect()

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
