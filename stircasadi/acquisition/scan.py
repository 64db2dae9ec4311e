"""Galvo scan controller: aims the laser at patch ``i`` (a microcontroller behind a serial link).

When to use: a rig that steers one pulsed laser over the illumination patches. The controller
holds a table of galvo angles per patch (loaded once with ``TABLE``); the host only says which
patch to aim at and waits for the acknowledgement that the mirrors have settled.

Wire protocol (ASCII lines, LF-terminated; every command gets exactly one reply line)::

    *IDN?              -> STIRCASADI,GALVO-SCAN,<serial>,<firmware>
    NPATCH?            -> NPATCH <n>                     (patches in the angle table)
    TABLE <i> <x> <y>  -> OK TABLE <i>                   (galvo angles in degrees for patch i)
    AIM <i>            -> OK AIM <i> <x_deg> <y_deg>     (sent after the mirrors settled)
    any error          -> ERR <code> <text>

The acknowledgement echoes the patch index; a reply for another patch, or anything that is not
``OK``/``ERR``, is a protocol error (never a silent mis-aim).

Neglects: galvo dynamics (the controller's settle time is all the host waits for).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import AcquisitionSettingsError, InstrumentError
from .serialio import Port, PortDevice, SerialSettings, instrument_error


@dataclass
class ScanSettings:
    """Settings of the galvo scan controller."""

    #: the serial link
    serial: SerialSettings = field(default_factory=SerialSettings)
    #: seconds the mirrors may take to settle before the AIM acknowledgement (added to timeout_s)
    settle_s: float = 0.05

    def validate(self) -> "ScanSettings":
        self.serial.validate()
        if not 0 <= self.settle_s <= 60:
            raise AcquisitionSettingsError(f"ScanSettings.settle_s must be in [0, 60] s; got {self.settle_s!r}.")
        return self


def parse_reply(device: str, command: str, line: str, expect: list[str]) -> list[str]:
    """Check a reply line is ``OK <expect...> ...`` (or the bare ``expect`` tokens) and return its tokens.

    ``ERR`` replies and mismatched echoes raise ``InstrumentError`` naming device and command.
    """
    toks = line.split()
    if toks and toks[0] == "ERR":
        raise instrument_error(device, command, f"device reported an error: {line!r}", line.encode(),
                               fix="See the controller's error code; check the patch index/table.")
    if toks and toks[0] == "OK":
        toks = toks[1:]
    if toks[:len(expect)] != expect:
        raise instrument_error(device, command,
                               f"unexpected reply (expected it to start with {' '.join(expect)!r})",
                               line.encode(), fix="Another program on the port, or a desynchronised "
                                                  "link; the command was not confirmed.")
    return toks[len(expect):]


class ScanController(PortDevice):
    """Driver of the galvo scan controller (context manager)."""

    def __init__(self, settings: ScanSettings):
        self.settings = settings.validate()
        self.port = Port(settings.serial, device=f"scan controller on {settings.serial.port}")
        self.identity = ""
        self.n_patches = 0

    def open(self) -> "ScanController":
        self.port.open()
        p = self.port
        self.identity = p.with_retries(lambda: p.query("*IDN?"), "*IDN?")

        def npatch() -> int:
            rest = parse_reply(p.device, "NPATCH?", p.query("NPATCH?"), ["NPATCH"])
            if len(rest) != 1 or not rest[0].isdigit():
                raise instrument_error(p.device, "NPATCH?", "patch count is not an integer",
                                       " ".join(rest).encode())
            return int(rest[0])
        self.n_patches = p.with_retries(npatch, "NPATCH?")
        return self

    def load_table(self, angles_deg) -> None:
        """Load the galvo angle table, one ``(x_deg, y_deg)`` per patch."""
        p = self.port
        for i, (x, y) in enumerate(angles_deg):
            cmd = f"TABLE {i} {float(x):.6f} {float(y):.6f}"
            p.with_retries(lambda: parse_reply(p.device, cmd, p.query(cmd), ["TABLE", str(i)]), cmd)
        self.n_patches = len(angles_deg)

    def aim(self, i: int) -> tuple[float, float]:
        """Aim at patch ``i``; returns the galvo angles the controller confirmed."""
        if not 0 <= int(i) < max(self.n_patches, 1):
            raise InstrumentError(f"{self.port.device}: patch {i} is outside the controller's table "
                                  f"of {self.n_patches} patches; load a table with load_table().")
        p = self.port
        cmd = f"AIM {int(i)}"

        def once():
            rest = parse_reply(p.device, cmd, p.query(cmd, timeout=self.settings.serial.timeout_s +
                                                      self.settings.settle_s), ["AIM", str(int(i))])
            try:
                return float(rest[0]), float(rest[1])
            except (IndexError, ValueError):
                raise instrument_error(p.device, cmd, "acknowledgement lacks the two galvo angles",
                                       " ".join(rest).encode()) from None
        return p.with_retries(once, cmd)

    def describe(self) -> dict:
        return {"identity": self.identity, "n_patches": self.n_patches,
                "settle_s": self.settings.settle_s, "serial": self.settings.serial.as_dict()}
