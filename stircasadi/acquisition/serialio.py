"""A binary-safe instrument link (serial or VISA): typed settings, deadlines, retries, clear errors.

When to use: every driver in ``stircasadi.acquisition`` talks through :class:`Port`; open one with
a :class:`SerialSettings` (only ``port`` is required, the rest have sensible defaults).

Transports: ``port`` is a serial device or pyserial URL (``/dev/ttyUSB0``, ``COM3``, ``loop://``),
opened with pyserial; or a VISA resource name (``TCPIP::192.168.1.5::INSTR``,
``TCPIP0::host::5025::SOCKET``, ``USB0::0x0699::0x0401::C000001::INSTR``, ``GPIB0::7::INSTR``),
opened with pyvisa (the optional extra ``stircasadi[visa]``; backend ``visa_library``, default
``@py`` = pyvisa-py, pure Python). The drivers and their wire protocols are the same on both.

Rules it enforces
-----------------
* Software flow control (XON/XOFF) is refused: 0x11/0x13 bytes occur in binary waveforms and
  histograms and would be eaten by the line discipline. Use ``rtscts=True`` for hardware flow
  control if the instrument needs it.
* Reads never trust a single ``read()`` call: each reply has a *deadline*
  ``timeout_s + n_bytes * per_byte_s`` that grows with the record length (the wire time of a
  64 kB waveform at 115200 baud is 5.7 s), and partial data is kept for the error message.
* Every failure raises :class:`~stircasadi.errors.InstrumentError` naming the device, the
  command and the bytes that arrived (``err.device``, ``err.command``, ``err.received``).
* Retries (``retries``) re-send a command after a timeout or a garbled reply, after draining the
  input; a disconnected port is never retried (``err.disconnected`` is True).

Neglects: on VISA, the bytes of a reply that times out half way are not shown in the error
(pyvisa drops them); VISA events and service requests (every reply is polled).
"""
from __future__ import annotations

import re
import time
from dataclasses import dataclass, asdict
from typing import Callable, TypeVar

from ..errors import AcquisitionSettingsError, InstrumentError
from .protocol import check_line, parse_block_header, preview

T = TypeVar("T")

#: seconds of one blocking read slice; every reply has its own, longer, deadline
_POLL_S = 0.02

_STANDARD_BAUDS = (300, 1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800,
                   500000, 576000, 921600, 1000000, 2000000, 3000000, 4000000)


@dataclass
class SerialSettings:
    """Settings of one serial link. Validated by :meth:`validate` (called by :class:`Port`)."""

    #: device path (``/dev/ttyUSB0``, ``COM3``) or a pyserial URL
    port: str = ""
    #: line rate in bits per second (a standard rate)
    baudrate: int = 115200
    #: seconds allowed for a short reply (a line, a block header)
    timeout_s: float = 2.0
    #: extra seconds per byte of a long reply; ``None``: twice the wire time, 20 / baudrate
    per_byte_s: float | None = None
    #: seconds allowed to write one command
    write_timeout_s: float = 2.0
    #: line terminator of commands and replies
    terminator: str = "\n"
    #: how often a command is re-sent after a timeout or a garbled reply (0: never)
    retries: int = 2
    #: seconds to wait before a retry, while stale input is drained
    retry_settle_s: float = 0.05
    #: software flow control; must stay False (binary data contain XON/XOFF bytes)
    xonxoff: bool = False
    #: hardware (RTS/CTS) flow control
    rtscts: bool = False
    #: largest binary block accepted, bytes (a garbage header cannot make us wait for 900 MB)
    max_block_bytes: int = 256 * 2**20
    #: longest text line accepted, bytes
    max_line_bytes: int = 65536
    #: pyvisa backend for VISA resource names ('@py': pyvisa-py; '': the system's VISA library)
    visa_library: str = "@py"

    def validate(self) -> "SerialSettings":
        if not isinstance(self.port, str) or not self.port:
            raise AcquisitionSettingsError(
                f"SerialSettings.port must name a serial device (e.g. '/dev/ttyUSB0', 'COM3'); "
                f"got {self.port!r}.")
        if not is_visa(self.port) and self.baudrate not in _STANDARD_BAUDS:
            raise AcquisitionSettingsError(
                f"SerialSettings.baudrate must be a standard rate {_STANDARD_BAUDS}; got "
                f"{self.baudrate!r}.")
        for name in ("timeout_s", "write_timeout_s"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not v > 0 or v > 3600:
                raise AcquisitionSettingsError(f"SerialSettings.{name} must be in (0, 3600] seconds; "
                                               f"got {v!r}.")
        if self.per_byte_s is not None and not (0 <= self.per_byte_s < 1):
            raise AcquisitionSettingsError(f"SerialSettings.per_byte_s must be in [0, 1) s or None; "
                                           f"got {self.per_byte_s!r}.")
        if not isinstance(self.retries, int) or not 0 <= self.retries <= 20:
            raise AcquisitionSettingsError(f"SerialSettings.retries must be an int in 0..20; got "
                                           f"{self.retries!r}.")
        if self.xonxoff:
            raise AcquisitionSettingsError(
                "SerialSettings.xonxoff=True is refused: XON/XOFF bytes (0x11, 0x13) occur inside "
                "binary waveforms and histograms and would be swallowed. Use rtscts=True for flow "
                "control, or leave both off.")
        if not self.terminator or len(self.terminator.encode("ascii", "replace")) > 2:
            raise AcquisitionSettingsError(f"SerialSettings.terminator must be 1-2 ASCII characters "
                                           f"such as '\\n' or '\\r\\n'; got {self.terminator!r}.")
        return self

    @property
    def per_byte(self) -> float:
        return self.per_byte_s if self.per_byte_s is not None else 20.0 / self.baudrate

    def timeout_for(self, n_bytes: int) -> float:
        """Deadline in seconds for a reply of ``n_bytes`` (grows with the record length)."""
        return float(self.timeout_s) + max(0, int(n_bytes)) * self.per_byte

    def as_dict(self) -> dict:
        return asdict(self)


_VISA = re.compile(r"^(TCPIP|USB|GPIB|ASRL|VXI|PXI|VICP)\d*::", re.IGNORECASE)


def is_visa(port: str) -> bool:
    """Whether ``port`` is a VISA resource name (``TCPIP::...``, ``USB0::...``) rather than a
    serial device."""
    return isinstance(port, str) and bool(_VISA.match(port))


class SerialIO:
    """The pyserial face of a link: reads return what arrived within one poll slice."""

    def __init__(self, io):
        self.io = io

    def read_upto(self, n: int, remaining_s: float) -> bytes:
        return self.io.read(n)

    def write(self, data: bytes) -> None:
        self.io.write(data)
        self.io.flush()

    def drain(self) -> None:
        self.io.reset_input_buffer()

    def close(self) -> None:
        self.io.close()


class VisaIO:
    """The pyvisa face of a link: a read returns all ``n`` bytes within ``remaining_s``, or none.

    (pyvisa drops the bytes of a read that times out, so a read never asks for more than the
    protocol says must come.) A lost connection raises ``ConnectionError``."""

    def __init__(self, resource):
        self.res = resource
        import pyvisa
        self._err = pyvisa.errors.VisaIOError
        self._tmo = pyvisa.constants.StatusCode.error_timeout

    def _read(self, n: int, remaining_s: float, term: bytes | None) -> bytes:
        from pyvisa import constants

        if term is not None:
            self.res.set_visa_attribute(constants.VI_ATTR_TERMCHAR, term[-1])
        self.res.set_visa_attribute(constants.VI_ATTR_TERMCHAR_EN, term is not None)
        self.res.timeout = max(1, int(remaining_s * 1000))
        try:
            return self.res.read_bytes(n, break_on_termchar=term is not None)
        except self._err as exc:
            if exc.error_code == self._tmo:
                return b""
            raise ConnectionError(str(exc)) from exc

    def read_upto(self, n: int, remaining_s: float) -> bytes:
        return self._read(n, remaining_s, None)

    def read_line(self, term: bytes, max_bytes: int, remaining_s: float) -> bytes:
        """One line ending in ``term`` (the VISA termination character), or b"" on timeout."""
        return self._read(max_bytes, remaining_s, term)

    def write(self, data: bytes) -> None:
        try:
            self.res.write_raw(data)
        except self._err as exc:
            raise ConnectionError(str(exc)) from exc

    def drain(self) -> None:
        while self.read_upto(1, 0.001):
            pass

    def close(self) -> None:
        self.res.close()


def _open_visa(s: "SerialSettings"):
    try:
        import pyvisa
    except ImportError as exc:
        raise ImportError("VISA resources need pyvisa: pip install 'stircasadi[visa]' "
                          "(pyvisa + pyvisa-py)") from exc
    rm = pyvisa.ResourceManager(s.visa_library) if s.visa_library else pyvisa.ResourceManager()
    res = rm.open_resource(s.port, open_timeout=int(s.timeout_s * 1000))
    res.read_termination = None
    res.write_termination = None
    res.timeout = int(s.write_timeout_s * 1000)
    return VisaIO(res)


def _io_errors() -> tuple:
    """Exceptions that mean the link itself failed (unplugged cable, hung-up pty)."""
    import serial
    try:
        import termios
        return (serial.SerialException, OSError, termios.error)
    except ImportError:  # pragma: no cover - Windows
        return (serial.SerialException, OSError)


def instrument_error(device: str, command: str | None, what: str, received: bytes = b"",
                     fix: str = "", disconnected: bool = False) -> InstrumentError:
    """Build an ``InstrumentError`` whose message names device, command and bytes received."""
    cmd = f"command {command!r}" if command else "no command"
    msg = f"{device}: {cmd}: {what}; received {preview(received)}."
    if fix:
        msg += " " + fix
    err = InstrumentError(msg)
    err.device = device
    err.command = command
    err.received = bytes(received)
    err.disconnected = disconnected
    return err


class PortDevice:
    """``close()`` and the context-manager protocol for drivers that own ``self.port`` and
    define ``open()`` (the scope, the scan controller and the counter)."""

    def close(self) -> None:
        self.port.close()

    def __enter__(self):
        return self.open()

    def __exit__(self, *exc):
        self.close()


class Port:
    """One open serial link to one instrument (context manager).

    Parameters
    ----------
    settings : SerialSettings
    device : str
        Name used in error messages ("scope", "scan controller", "counter").
    """

    def __init__(self, settings: SerialSettings, device: str):
        self.settings = settings.validate()
        self.device = device
        self.io = None
        self.term = settings.terminator.encode("ascii")
        #: number of retries spent so far (recorded in provenance)
        self.retries_used = 0

    # ------------------------------------------------------------------ open/close
    def open(self) -> "Port":
        s = self.settings
        if is_visa(s.port):
            try:
                self.io = _open_visa(s)
            except Exception as exc:  # ImportError, VisaIOError, ValueError on a malformed name
                raise instrument_error(self.device, None, f"cannot open VISA resource {s.port!r} ({exc})",
                                       fix="Check the address, that the instrument is on the network "
                                           "and that pyvisa is installed (stircasadi[visa]).",
                                       disconnected=True) from exc
            self.io.drain()
            return self
        import serial

        try:
            io = serial.serial_for_url(s.port, do_not_open=True)
            io.baudrate = s.baudrate
            io.bytesize = serial.EIGHTBITS
            io.parity = serial.PARITY_NONE
            io.stopbits = serial.STOPBITS_ONE
            io.xonxoff = False
            io.rtscts = bool(s.rtscts)
            io.timeout = _POLL_S  # reads poll in short slices against their own deadline
            io.write_timeout = s.write_timeout_s
            io.open()
        except _io_errors() + (ValueError,) as exc:
            raise instrument_error(self.device, None, f"cannot open port {s.port!r} ({exc})",
                                   fix="Check the cable, the port name and that no other program "
                                       "holds the port.", disconnected=True) from exc
        self.io = SerialIO(io)
        try:
            self.io.drain()
        except Exception:  # pragma: no cover - some URL handlers lack it
            pass
        return self

    def close(self) -> None:
        if self.io is not None:
            try:
                self.io.close()
            except Exception:  # pragma: no cover - closing a dead port
                pass
            self.io = None

    def __enter__(self) -> "Port":
        return self.open() if self.io is None else self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ raw I/O
    def _need_open(self, command: str | None) -> None:
        if self.io is None:
            raise instrument_error(self.device, command, "port is not open",
                                   fix="Use 'with Port(...)' or call open().")

    def write(self, command: str) -> None:
        """Send one command line (the terminator is appended)."""
        self._need_open(command)
        try:
            self.io.drain()  # stale replies never answer a new command
            self.io.write(command.encode("ascii") + self.term)
        except _io_errors() as exc:
            raise instrument_error(self.device, command, f"write failed, device disconnected? ({exc})",
                                   fix="Reconnect the instrument and resume the capture.",
                                   disconnected=True) from exc

    def _read(self, n: int, deadline: float, command: str, sofar: bytes) -> bytes:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return b""
        try:
            return self.io.read_upto(n, remaining)
        except _io_errors() as exc:
            raise instrument_error(self.device, command, f"device disconnected during the reply ({exc})",
                                   sofar, fix="Reconnect the instrument and resume the capture.",
                                   disconnected=True) from exc

    def read_exact(self, n: int, command: str, timeout: float | None = None, sofar: bytes = b"") -> bytes:
        """Read exactly ``n`` bytes before the deadline or raise (keeping what arrived)."""
        self._need_open(command)
        timeout = self.settings.timeout_for(n) if timeout is None else timeout
        deadline = time.monotonic() + timeout
        buf = bytearray()
        while len(buf) < n:
            chunk = self._read(n - len(buf), deadline, command, sofar + bytes(buf))
            if not chunk:
                if time.monotonic() >= deadline:
                    raise instrument_error(
                        self.device, command,
                        f"timed out after {timeout:.3g} s waiting for {n} bytes, {len(buf)} arrived "
                        "(stalled device or truncated block)", sofar + bytes(buf),
                        fix="Check the instrument; raise SerialSettings.timeout_s/per_byte_s for "
                            "long records.")
                continue
            buf += chunk
        return bytes(buf)

    def read_line(self, command: str, timeout: float | None = None) -> str:
        """Read one terminated line of printable ASCII (terminator stripped)."""
        self._need_open(command)
        timeout = self.settings.timeout_s if timeout is None else timeout
        deadline = time.monotonic() + timeout
        buf = bytearray()
        if isinstance(self.io, VisaIO):  # whole lines at once (byte-wise VISA reads are slow)
            try:
                buf += self.io.read_line(self.term, self.settings.max_line_bytes + 1, timeout)
            except _io_errors() as exc:
                raise instrument_error(self.device, command, f"device disconnected during the reply ({exc})",
                                       fix="Reconnect the instrument and resume the capture.",
                                       disconnected=True) from exc
        while not buf.endswith(self.term):
            if len(buf) > self.settings.max_line_bytes:
                raise instrument_error(self.device, command,
                                       f"reply line longer than {self.settings.max_line_bytes} bytes "
                                       "without a terminator", bytes(buf))
            chunk = self._read(1, deadline, command, bytes(buf))
            if not chunk:
                if time.monotonic() >= deadline:
                    raise instrument_error(
                        self.device, command,
                        f"no complete reply line (terminator {self.term!r}) within {timeout:.3g} s",
                        bytes(buf), fix="Check the cable, the baud rate and the terminator setting.")
                continue
            buf += chunk
        try:
            return check_line(bytes(buf[:-len(self.term)]))
        except InstrumentError as exc:
            raise instrument_error(self.device, command, str(exc).rstrip("."), bytes(buf),
                                   fix="Check the baud rate; noise on the line?") from None

    def read_block(self, command: str, allowed_prefix: bytes = b"", expect: int | None = None,
                   limit: int | None = None) -> bytes:
        """Read one IEEE-488.2 definite-length block; returns the payload.

        Leading whitespace and ``allowed_prefix`` (e.g. ``b':CURVE '``) before ``#`` are skipped;
        anything else is garbage and raises. ``expect`` (the length the protocol requires, e.g.
        record length x bytes per point) or ``limit`` (the most it allows) are checked against
        the header *before* the payload is read, so a corrupt length (``#9099999999``) fails at
        once instead of waiting for bytes that never come.
        """
        self._need_open(command)
        s = self.settings
        deadline = time.monotonic() + s.timeout_s
        pre = bytearray()
        while True:
            c = self._read(1, deadline, command, bytes(pre))
            if not c:
                if time.monotonic() >= deadline:
                    raise instrument_error(self.device, command,
                                           f"no binary block ('#') within {s.timeout_s:.3g} s", bytes(pre),
                                           fix="Check that the instrument is armed and the command "
                                               "is supported.")
                continue
            if c == b"#":
                break
            pre += c
            stripped = bytes(pre).lstrip(b" \r\n")
            if len(pre) > 64 or not (allowed_prefix.startswith(stripped) or stripped == b""):
                raise instrument_error(self.device, command,
                                       "garbage before the binary block header '#'", bytes(pre))
        head = b"#" + self.read_exact(1, command, s.timeout_s, sofar=b"#")
        try:
            if not head[1:2].isdigit():
                parse_block_header(head)
            nd = int(head[1:2])
            if nd == 0:
                parse_block_header(head)
            head += self.read_exact(nd, command, s.timeout_s, sofar=head)
            hlen, length = parse_block_header(head)
        except InstrumentError as exc:
            if getattr(exc, "device", None):
                raise
            raise instrument_error(self.device, command, str(exc).rstrip("."), head) from None
        if expect is not None and length != expect:
            raise instrument_error(self.device, command,
                                   f"block header announces {length} bytes but the preamble allows "
                                   f"exactly {expect} (record length x bytes per point): a corrupt "
                                   "length field", head, fix="Check the link (noise?) and the "
                                   "instrument's DATA settings; the read was not attempted.")
        if limit is not None and length > limit:
            raise instrument_error(self.device, command,
                                   f"block header announces {length} bytes, more than the {limit} the "
                                   "record can hold: a corrupt length field", head,
                                   fix="Check the link (noise?) and the instrument's settings.")
        if length > s.max_block_bytes:
            raise instrument_error(self.device, command,
                                   f"block header announces {length} bytes, more than "
                                   f"max_block_bytes={s.max_block_bytes}", head,
                                   fix="Raise SerialSettings.max_block_bytes if this is genuine.")
        payload = self.read_exact(length, command, s.timeout_for(length), sofar=head)
        # swallow the trailing terminator if the instrument sends one
        try:
            tail = self.io.read_upto(len(self.term), _POLL_S)
        except Exception:
            tail = b""
        if tail and tail != self.term[:len(tail)]:
            raise instrument_error(self.device, command,
                                   f"unexpected byte(s) after a {length}-byte block (expected the "
                                   "terminator)", head + payload[-16:] + tail)
        return payload

    # ------------------------------------------------------------------ transactions
    def query(self, command: str, timeout: float | None = None) -> str:
        """Write ``command`` and read one reply line."""
        self.write(command)
        return self.read_line(command, timeout)

    def query_block(self, command: str, allowed_prefix: bytes = b"", expect: int | None = None,
                    limit: int | None = None) -> bytes:
        """Write ``command`` and read one binary block (see :meth:`read_block`)."""
        self.write(command)
        return self.read_block(command, allowed_prefix, expect=expect, limit=limit)

    def with_retries(self, fn: Callable[[], T], command: str) -> T:
        """Run ``fn`` (one command/reply exchange) up to ``retries + 1`` times.

        A disconnected port is not retried. The last error is raised, with the attempt count.
        """
        attempts = self.settings.retries + 1
        for k in range(attempts):
            try:
                return fn()
            except InstrumentError as exc:
                if getattr(exc, "disconnected", False) or k == attempts - 1:
                    if attempts > 1 and not getattr(exc, "disconnected", False):
                        exc.args = (exc.args[0] + f" (failed {attempts} attempts)",)
                    raise
                self.retries_used += 1
                time.sleep(self.settings.retry_settle_s)
                try:
                    self.io.drain()
                except Exception:  # pragma: no cover
                    pass
        raise AssertionError("unreachable")  # pragma: no cover
