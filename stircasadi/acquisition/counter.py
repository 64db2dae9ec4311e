"""Histogramming photon counter (TCSPC board with a SPAD per channel) over a serial link.

When to use: today's rigs (galvo-steered pulsed laser, SPADs, time-correlated single-photon
counting). Channel ``k`` is the SPAD that watches observed patch ``k``. For each aimed patch the
host starts an accumulation over ``n`` laser sync periods and reads one histogram per channel;
those counts become ``stir[i, k, :]``.

Wire protocol (ASCII command lines, LF-terminated; histograms as IEEE-488.2 blocks)::

    *IDN?            -> PICOEMU,HISTO-8,<serial>,<firmware>
    HIST:NBIN?       -> <n_bins>                        (integer)
    HIST:RES?        -> <bin width in picoseconds>      (float)
    HIST:OFFS?       -> <time of bin 0's left edge after the sync, picoseconds>
    HIST:NCH?        -> <number of channels>
    SYNC:RATE?       -> <laser repetition rate, Hz>
    ACQ <n>          -> OK ACQ <n>                      (after n sync periods were accumulated)
    HIST? <k>        -> #<d><len><n_bins little-endian uint32 counts>\\n
    any error        -> ERR <code> <text>

The ``ACQ`` reply comes after ``n / rate`` seconds, so its deadline grows with ``n``; a histogram
block must hold exactly ``4 * n_bins`` bytes.

Units at the edge: ``bin_width = HIST:RES * 1e-12 * c``, ``start = HIST:OFFS * 1e-12 * c +
sync_offset_m`` (metres of path), where ``sync_offset_m`` is the path length between emission
and the sync edge (calibrate with :func:`stircasadi.acquisition.calibration.time_zero`).

Neglects: pile-up and dead time at acquisition time (correct them afterwards with
:func:`stircasadi.acquisition.calibration.pileup_correct`), channel-to-channel skew.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..constants import ps_to_m
from ..errors import AcquisitionSettingsError, InstrumentError
from ..timegrid import TimeGrid
from .scan import parse_reply
from .serialio import Port, PortDevice, SerialSettings, instrument_error


@dataclass
class CounterSettings:
    """Settings of a histogramming counter."""

    #: the serial link
    serial: SerialSettings = field(default_factory=SerialSettings)
    #: channels to read, one per observed patch, in observed-id order (0-based)
    channels: tuple = (0,)
    #: path length (m) from emission to the sync edge (added to the histogram offset)
    sync_offset_m: float = 0.0

    def validate(self) -> "CounterSettings":
        self.serial.validate()
        chans = tuple(self.channels)
        if not chans or any(not isinstance(c, int) or not 0 <= c < 64 for c in chans) or \
                len(set(chans)) != len(chans):
            raise AcquisitionSettingsError(f"CounterSettings.channels must be distinct ints in 0..63; "
                                           f"got {self.channels!r}.")
        self.channels = chans
        if not math.isfinite(self.sync_offset_m):
            raise AcquisitionSettingsError("CounterSettings.sync_offset_m must be finite metres.")
        return self


def decode_histogram(payload: bytes, n_bins: int) -> np.ndarray:
    """Little-endian uint32 counts -> float64 array of ``n_bins``; raises on a wrong length."""
    if len(payload) != 4 * n_bins:
        raise InstrumentError(f"histogram block holds {len(payload)} bytes; expected 4 x n_bins = "
                              f"{4 * n_bins} (uint32 per bin).")
    return np.frombuffer(payload, dtype="<u4").astype(np.float64)


class HistogramCounter(PortDevice):
    """Driver of the histogramming counter as a STIR detector (context manager)."""

    kind = "counter"

    def __init__(self, settings: CounterSettings):
        self.settings = settings.validate()
        self.port = Port(settings.serial, device=f"counter on {settings.serial.port}")
        self.identity = ""
        self.n_bins = 0
        self.res_ps = 0.0
        self.offs_ps = 0.0
        self.sync_rate_hz = 0.0
        self.n_channels = 0

    def _number(self, cmd: str, integer: bool = False):
        p = self.port

        def once():
            line = p.query(cmd)
            try:
                v = float(line)
            except ValueError:
                raise instrument_error(p.device, cmd, "reply is not a number", line.encode()) from None
            if not math.isfinite(v) or (integer and v != int(v)):
                raise instrument_error(p.device, cmd, "reply is not a finite "
                                       + ("integer" if integer else "number"), line.encode())
            return int(v) if integer else v
        return p.with_retries(once, cmd)

    def open(self) -> "HistogramCounter":
        self.port.open()
        p = self.port
        self.identity = p.with_retries(lambda: p.query("*IDN?"), "*IDN?")
        self.n_bins = self._number("HIST:NBIN?", integer=True)
        self.res_ps = self._number("HIST:RES?")
        self.offs_ps = self._number("HIST:OFFS?")
        self.n_channels = self._number("HIST:NCH?", integer=True)
        self.sync_rate_hz = self._number("SYNC:RATE?")
        if self.n_bins < 1 or not self.res_ps > 0 or not self.sync_rate_hz > 0:
            raise instrument_error(p.device, "HIST:NBIN?/HIST:RES?/SYNC:RATE?",
                                   f"implausible configuration n_bins={self.n_bins}, "
                                   f"res={self.res_ps} ps, rate={self.sync_rate_hz} Hz")
        bad = [c for c in self.settings.channels if c >= self.n_channels]
        if bad:
            raise InstrumentError(f"{p.device}: channels {bad} requested but the counter has "
                                  f"{self.n_channels} (0..{self.n_channels - 1}).")
        return self

    @property
    def n_observed(self) -> int:
        return len(self.settings.channels)

    def grid(self) -> TimeGrid:
        return TimeGrid(ps_to_m(self.offs_ps) + self.settings.sync_offset_m, ps_to_m(self.res_ps),
                        self.n_bins)

    def acquire(self, shots: int) -> np.ndarray:
        """Accumulate ``shots`` sync periods and read every channel: ``(n_observed, n_bins)`` counts."""
        p = self.port
        n = int(shots)
        cmd = f"ACQ {n}"
        wait = self.settings.serial.timeout_s + 1.5 * n / self.sync_rate_hz
        p.with_retries(lambda: parse_reply(p.device, cmd, p.query(cmd, timeout=wait), ["ACQ", str(n)]), cmd)
        out = np.empty((self.n_observed, self.n_bins))
        for j, ch in enumerate(self.settings.channels):
            hc = f"HIST? {ch}"

            def once():
                payload = p.query_block(hc, expect=4 * self.n_bins)
                try:
                    return decode_histogram(payload, self.n_bins)
                except InstrumentError as exc:
                    raise instrument_error(p.device, hc, str(exc).rstrip("."), payload) from None
            out[j] = p.with_retries(once, hc)
        return out

    def describe(self) -> dict:
        return {"detector": "counter", "identity": self.identity, "n_bins": self.n_bins,
                "bin_width_ps": self.res_ps, "offset_ps": self.offs_ps,
                "sync_rate_hz": self.sync_rate_hz, "channels": list(self.settings.channels),
                "sync_offset_m": self.settings.sync_offset_m, "unit": "counts",
                "serial": self.settings.serial.as_dict()}
