"""SCPI sampling oscilloscopes over a serial link: Tektronix-style and LeCroy-style waveforms.

When to use: the seed's rig (femtosecond laser, photodiodes, sampling oscilloscope). Channel
``CHn`` watches observed patch ``n-1``; each acquisition returns one waveform per channel, which
becomes ``stir[i, n-1, :]`` while the scan controller aims the laser at patch ``i``. Shots are
averaged on the host (each waveform query is one fresh acquisition).

Wire protocol, Tektronix dialect (ASCII commands, LF-terminated)::

    *IDN?                 -> TEKTRONIX,DSA8300,B0xxxx,CF:91.1CT FV:1.0
    HEADER ON / VERBOSE ON   (so WFMOUTPRE? names every field)
    DATA:ENCDG RIBINARY ; DATA:WIDTH 2
    DATA:SOURCE CH1;:WFMOUTPRE?   (one compound line)
                          -> :WFMOUTPRE:BYT_NR 2;BIT_NR 16;ENCDG BIN;BN_FMT RI;BYT_OR MSB;NR_PT 1000;
                             WFID "Ch1 ...";PT_FMT Y;XUNIT "s";XINCR 4.0E-12;XZERO 1.0E-9;PT_OFF 0;
                             YUNIT "V";YMULT 1.5625E-5;YOFF 0.0E0;YZERO 0.0E0
    CURVE?                -> :CURVE #42000<2000 bytes>\\n   (IEEE-488.2 definite-length block)

DPO/MDO/MSO families add fields (``PT_ORDER``, ``DOMAIN``, ``WFMTYPE``, ``CENTERFREQUENCY``,
``SPAN``, ``REFLEVEL``...): fields the driver does not use are kept in ``Waveform.header`` and
recorded in the capture's provenance, never fatal; only ``DOMAIN`` other than ``TIME`` (a
spectrum) is refused.

Checks against a scope that misbehaves: every waveform's channel is verified against the
preamble (``WFID "Ch2, ..."``; when the WFID names no channel, ``DATA:SOURCE?``), so a scope that
ignores ``DATA:SOURCE`` is caught; the ``CURVE?`` block must announce exactly
``NR_PT x BYT_NR`` bytes, checked on its header before the payload is read (a corrupt
``#9099999999`` fails at once). LeCroy: ``WAVE_SOURCE`` (i16 @344: 0 = C1 ... 3 = C4) must be the
channel asked for, and a block may not exceed the descriptor plus the record.

Scaling (Tektronix programmer manuals): ``volts[k] = (raw[k] - YOFF) * YMULT + YZERO`` and
``t[k] = XZERO + XINCR * (k - PT_OFF)`` seconds after the trigger.

Wire protocol, LeCroy dialect::

    CHDR OFF ; CFMT DEF9,WORD,BIN ; CORD LO
    C1:WF? ALL            -> #9000002346<WAVEDESC descriptor, 346 bytes><data array>

The LECROY_2_3 descriptor (template offsets, bytes): COMM_TYPE i16 @32 (0 byte, 1 word),
COMM_ORDER i16 @34 (0 big-, 1 little-endian), WAVE_DESCRIPTOR i32 @36, USER_TEXT i32 @40,
TRIGTIME_ARRAY i32 @48, RIS_TIME_ARRAY i32 @52, WAVE_ARRAY_1 i32 @60, WAVE_ARRAY_COUNT i32 @116,
VERTICAL_GAIN f32 @156, VERTICAL_OFFSET f32 @160, HORIZ_INTERVAL f32 @176, HORIZ_OFFSET f64 @180,
VERTUNIT char[48] @196, HORUNIT char[48] @244, WAVE_SOURCE i16 @344. Scaling: ``volts = GAIN * raw - OFFSET``,
``t[k] = HORIZ_OFFSET + k * HORIZ_INTERVAL``.

Units at the edge: samples are taken as bin centres, so the time grid is
``start = (t[0] - dt/2) * c + trigger_offset_m`` and ``bin_width = dt * c`` (metres of path).
``trigger_offset_m`` is the path length travelled between emission and the scope's t = 0
(cable and trigger delays); calibrate it with :func:`stircasadi.acquisition.calibration.time_zero`.

Neglects: the scope's own bandwidth (it is part of the impulse response), ASCII encodings,
envelope waveforms, sequence/segmented records.
"""
from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass, field

import numpy as np

from ..constants import C
from ..errors import AcquisitionSettingsError, InstrumentError, TimeGridError
from ..timegrid import TimeGrid
from .protocol import preview
from .serialio import Port, PortDevice, SerialSettings, instrument_error

WAVEDESC_LEN = 346


@dataclass
class Waveform:
    """One waveform in the instrument's units: ``volts[k]`` sampled at ``t0_s + k*dt_s`` seconds."""

    volts: np.ndarray
    t0_s: float
    dt_s: float
    header: dict = field(default_factory=dict)

    def grid(self, trigger_offset_m: float = 0.0) -> TimeGrid:
        """The time grid in metres of path (samples are bin centres)."""
        try:
            return TimeGrid((self.t0_s - 0.5 * self.dt_s) * C + trigger_offset_m, self.dt_s * C,
                            int(self.volts.shape[-1]))
        except TimeGridError as exc:
            raise InstrumentError(f"waveform time axis (t0={self.t0_s!r} s, dt={self.dt_s!r} s) is "
                                  f"not usable: {exc}") from exc


# ---------------------------------------------------------------------- Tektronix
#: the preamble fields the driver uses; any other field is kept and recorded
_TEK_KEYS = {"BYT_NR", "BIT_NR", "ENCDG", "BN_FMT", "BYT_OR", "NR_PT", "WFID", "PT_FMT", "XUNIT",
             "XINCR", "XZERO", "PT_OFF", "YUNIT", "YMULT", "YOFF", "YZERO", "NR_FR"}
_QUOTED = ("WFID", "XUNIT", "YUNIT")
_TEK_REQUIRED = ("BYT_NR", "BN_FMT", "BYT_OR", "NR_PT", "XUNIT", "XINCR", "XZERO", "PT_OFF",
                 "YUNIT", "YMULT", "YOFF", "YZERO")


def _split_fields(text: str) -> list[str]:
    out, cur, quoted = [], [], False
    for ch in text:
        if ch == '"':
            quoted = not quoted
        if ch == ";" and not quoted:
            out.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    out.append("".join(cur))
    return [f.strip() for f in out if f.strip()]


def parse_wfmoutpre(text: str) -> dict:
    """Parse a verbose ``WFMOUTPRE?`` reply (``HEADER ON; VERBOSE ON``) into a dict.

    Numbers become floats/ints, strings lose their quotes; fields the driver does not use (DPO,
    MDO, MSO: ``DOMAIN``, ``WFMTYPE``, ``CENTERFREQUENCY``...) are kept as text. Raises
    ``InstrumentError`` for a missing field, a non-numeric number, the terse (header-off) form
    or a frequency-domain record.
    """
    if not isinstance(text, str):
        raise InstrumentError(f"WFMOUTPRE? reply must be text; got {type(text).__name__}.")
    body = text.strip()
    for prefix in (":WFMOUTPRE:", ":WFMO:", "WFMOUTPRE:", "WFMO:"):
        if body.upper().startswith(prefix):
            body = body[len(prefix):]
            break
    out: dict = {}
    for item in _split_fields(body):
        if item.startswith(":"):
            item = item.lstrip(":")
            if item.upper().startswith(("WFMOUTPRE:", "WFMO:")):
                item = item.split(":", 1)[1]
        key, _, val = item.partition(" ")
        key = key.upper()
        if not val:
            raise InstrumentError(
                f"WFMOUTPRE? field {item!r} has no keyword/value pair; the driver needs the verbose "
                "form (send 'HEADER ON' and 'VERBOSE ON' first). Reply was: " + repr(text[:200]))
        val = val.strip()
        if val.startswith('"') and val.endswith('"') and len(val) >= 2:
            out[key] = val[1:-1]
        else:
            out[key] = val
    missing = [k for k in _TEK_REQUIRED if k not in out]
    if missing:
        raise InstrumentError(f"WFMOUTPRE? reply lacks field(s) {missing}; got {sorted(out)}.")
    for k in ("BYT_NR", "NR_PT", "BIT_NR", "NR_FR"):
        if k in out:
            try:
                v = float(out[k])
            except ValueError:
                raise InstrumentError(f"WFMOUTPRE? field {k} must be an integer; got {out[k]!r}.") from None
            if not math.isfinite(v) or v != int(v):
                raise InstrumentError(f"WFMOUTPRE? field {k} must be an integer; got {out[k]!r}.")
            out[k] = int(v)
    for k in ("XINCR", "XZERO", "PT_OFF", "YMULT", "YOFF", "YZERO"):
        try:
            out[k] = float(out[k])
        except ValueError:
            raise InstrumentError(f"WFMOUTPRE? field {k} must be a number; got {out[k]!r}.") from None
        if not math.isfinite(out[k]):
            raise InstrumentError(f"WFMOUTPRE? field {k} must be finite; got {out[k]!r}.")
    for k in ("BN_FMT", "BYT_OR", "ENCDG", "PT_FMT", "XUNIT", "YUNIT"):
        if k in out:
            out[k] = str(out[k]).strip().upper()
    domain = str(out.get("DOMAIN", "TIME")).strip().upper()
    if domain != "TIME":
        raise InstrumentError(f"WFMOUTPRE? says DOMAIN {domain}: a frequency-domain (spectrum) record, "
                              "not a time waveform; select a time-domain channel (DATA:SOURCE CHn).")
    return out


def preamble_extras(pre: dict) -> dict:
    """The preamble fields the driver does not use (recorded in provenance)."""
    return {k: v for k, v in pre.items() if k not in _TEK_KEYS}


def wfid_channel(wfid) -> int | None:
    """The channel number a Tektronix ``WFID`` names (``"Ch2, DC coupling..."`` -> 2), or None."""
    m = re.match(r"\s*(?:CH|C)\s*(\d+)\b", str(wfid or ""), re.IGNORECASE)
    return int(m.group(1)) if m else None


def tek_waveform(pre: dict, payload: bytes) -> Waveform:
    """Scale a Tektronix ``CURVE?`` payload with its preamble into volts and seconds."""
    if pre.get("ENCDG", "BIN") not in ("BIN", "BINARY"):
        raise InstrumentError(f"ENCDG {pre['ENCDG']!r} is not supported; allowed: BIN. Send "
                              "'DATA:ENCDG RIBINARY'.")
    if pre.get("PT_FMT", "Y") != "Y":
        raise InstrumentError(f"PT_FMT {pre['PT_FMT']!r} (envelope) is not supported; allowed: Y.")
    if pre["XUNIT"] != "S":
        raise InstrumentError(f"XUNIT {pre['XUNIT']!r} is not supported; allowed: 's' (seconds). "
                              "Set the horizontal axis to time.")
    if pre["YUNIT"] != "V":
        raise InstrumentError(f"YUNIT {pre['YUNIT']!r} is not supported; allowed: 'V'.")
    nb = pre["BYT_NR"]
    if nb not in (1, 2, 4):
        raise InstrumentError(f"BYT_NR must be 1, 2 or 4; got {nb!r}.")
    fmt = pre["BN_FMT"]
    if fmt not in ("RI", "RP"):
        raise InstrumentError(f"BN_FMT must be RI (signed) or RP (unsigned); got {fmt!r}.")
    order = pre["BYT_OR"]
    if order not in ("MSB", "LSB"):
        raise InstrumentError(f"BYT_OR must be MSB or LSB; got {order!r}.")
    n = pre["NR_PT"]
    if n < 1:
        raise InstrumentError(f"NR_PT must be >= 1; got {n}.")
    if len(payload) != n * nb:
        raise InstrumentError(f"CURVE? block holds {len(payload)} bytes but the preamble says "
                              f"NR_PT={n} x BYT_NR={nb} = {n * nb}; the record is truncated or the "
                              "preamble is stale.")
    if not pre["XINCR"] > 0:
        raise InstrumentError(f"XINCR must be > 0 s; got {pre['XINCR']!r}.")
    if pre["YMULT"] == 0:
        raise InstrumentError("YMULT is 0; the waveform cannot be scaled to volts.")
    dt = np.dtype(("i" if fmt == "RI" else "u") + str(nb)).newbyteorder(">" if order == "MSB" else "<")
    raw = np.frombuffer(payload, dtype=dt).astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        volts = (raw - pre["YOFF"]) * pre["YMULT"] + pre["YZERO"]
    if not np.all(np.isfinite(volts)):
        raise InstrumentError("scaled waveform overflows (YMULT/YOFF/YZERO out of range).")
    t0 = pre["XZERO"] - pre["PT_OFF"] * pre["XINCR"]
    return Waveform(volts=volts, t0_s=float(t0), dt_s=float(pre["XINCR"]), header=dict(pre))


def tek_preamble_text(pre: dict) -> str:
    """Format a preamble dict as the verbose ``WFMOUTPRE?`` reply (used by the emulator)."""
    parts = []
    for k, v in pre.items():
        if k in _QUOTED:
            parts.append(f'{k} "{v}"')
        elif isinstance(v, float):
            parts.append(f"{k} {v:.9E}")
        else:
            parts.append(f"{k} {v}")
    return ":WFMOUTPRE:" + ";".join(parts)


# ---------------------------------------------------------------------- LeCroy
def lecroy_waveform(block: bytes) -> Waveform:
    """Decode a LeCroy ``WF? ALL`` payload (WAVEDESC descriptor + data array) into volts, seconds."""
    block = bytes(block)
    i = block.find(b"WAVEDESC")
    if i < 0 or i > 64:
        raise InstrumentError(f"LeCroy waveform has no 'WAVEDESC' descriptor at its start; got "
                              f"{preview(block[:64])}.")
    d = block[i:]
    if len(d) < WAVEDESC_LEN:
        raise InstrumentError(f"LeCroy descriptor truncated: {len(d)} bytes, needs {WAVEDESC_LEN}.")
    order_le = struct.unpack_from("<h", d, 34)[0]
    order_be = struct.unpack_from(">h", d, 34)[0]
    if order_le == 1:
        e = "<"
    elif order_be == 0 and order_le == 0:
        e = ">"
    else:
        raise InstrumentError(f"LeCroy COMM_ORDER must be 0 (HIFIRST) or 1 (LOFIRST); got bytes "
                              f"{d[34:36]!r}.")
    comm_type = struct.unpack_from(e + "h", d, 32)[0]
    if comm_type not in (0, 1):
        raise InstrumentError(f"LeCroy COMM_TYPE must be 0 (byte) or 1 (word); got {comm_type}.")
    wave_desc, user_text = struct.unpack_from(e + "ii", d, 36)
    trig, ris = struct.unpack_from(e + "ii", d, 48)
    array1 = struct.unpack_from(e + "i", d, 60)[0]
    count = struct.unpack_from(e + "i", d, 116)[0]
    gain, offset = struct.unpack_from(e + "ff", d, 156)
    hint = struct.unpack_from(e + "f", d, 176)[0]
    hoff = struct.unpack_from(e + "d", d, 180)[0]
    vunit = d[196:244].split(b"\0", 1)[0].decode("ascii", "replace").strip().upper()
    hunit = d[244:292].split(b"\0", 1)[0].decode("ascii", "replace").strip().upper()
    for name, v in (("WAVE_DESCRIPTOR", wave_desc), ("USER_TEXT", user_text),
                    ("TRIGTIME_ARRAY", trig), ("RIS_TIME_ARRAY", ris), ("WAVE_ARRAY_1", array1),
                    ("WAVE_ARRAY_COUNT", count)):
        if v < 0:
            raise InstrumentError(f"LeCroy descriptor field {name} is negative ({v}).")
    if wave_desc < WAVEDESC_LEN:
        raise InstrumentError(f"LeCroy WAVE_DESCRIPTOR length {wave_desc} < {WAVEDESC_LEN}.")
    width = 1 if comm_type == 0 else 2
    if count < 1 or array1 != count * width:
        raise InstrumentError(f"LeCroy WAVE_ARRAY_1={array1} bytes does not match WAVE_ARRAY_COUNT="
                              f"{count} x {width} bytes.")
    start = wave_desc + user_text + trig + ris
    data = d[start:start + array1]
    if len(data) != array1:
        raise InstrumentError(f"LeCroy data array truncated: {len(data)} of {array1} bytes arrived.")
    for name, v in (("VERTICAL_GAIN", gain), ("VERTICAL_OFFSET", offset),
                    ("HORIZ_INTERVAL", hint), ("HORIZ_OFFSET", hoff)):
        if not math.isfinite(v):
            raise InstrumentError(f"LeCroy descriptor field {name} is not finite ({v}).")
    if not hint > 0:
        raise InstrumentError(f"LeCroy HORIZ_INTERVAL must be > 0 s; got {hint}.")
    if gain == 0:
        raise InstrumentError("LeCroy VERTICAL_GAIN is 0; the waveform cannot be scaled to volts.")
    if vunit != "V":
        raise InstrumentError(f"LeCroy VERTUNIT {vunit!r} is not supported; allowed: 'V'.")
    if hunit != "S":
        raise InstrumentError(f"LeCroy HORUNIT {hunit!r} is not supported; allowed: 'S' (seconds).")
    raw = np.frombuffer(data, dtype=np.dtype("i1" if width == 1 else e + "i2")).astype(np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        volts = gain * raw - offset
    if not np.all(np.isfinite(volts)):
        raise InstrumentError("LeCroy scaled waveform overflows (VERTICAL_GAIN/OFFSET out of range).")
    hdr = {"COMM_TYPE": comm_type, "COMM_ORDER": 1 if e == "<" else 0, "WAVE_ARRAY_COUNT": count,
           "VERTICAL_GAIN": gain, "VERTICAL_OFFSET": offset, "HORIZ_INTERVAL": hint,
           "HORIZ_OFFSET": hoff, "WAVE_SOURCE": struct.unpack_from(e + "h", d, 344)[0]}
    return Waveform(volts=volts, t0_s=float(hoff), dt_s=float(hint), header=hdr)


def lecroy_encode(raw: np.ndarray, gain: float, offset: float, hint: float, hoff: float,
                  word: bool = True, little: bool = True, vunit: str = "V", hunit: str = "S",
                  source: int = 9) -> bytes:
    """Build a LECROY_2_3 ``WF? ALL`` payload (used by the emulator and the tests)."""
    e = "<" if little else ">"
    raw = np.asarray(raw)
    data = raw.astype(e + ("i2" if word else "i1")).tobytes()
    d = bytearray(WAVEDESC_LEN)
    d[0:8] = b"WAVEDESC"
    d[16:26] = b"LECROY_2_3"
    struct.pack_into(e + "hh", d, 32, 1 if word else 0, 1 if little else 0)
    struct.pack_into(e + "ii", d, 36, WAVEDESC_LEN, 0)
    struct.pack_into(e + "i", d, 60, len(data))
    struct.pack_into(e + "i", d, 116, raw.size)
    struct.pack_into(e + "ff", d, 156, gain, offset)
    struct.pack_into(e + "f", d, 176, hint)
    struct.pack_into(e + "d", d, 180, hoff)
    d[196:196 + len(vunit)] = vunit.encode("ascii")
    d[244:244 + len(hunit)] = hunit.encode("ascii")
    struct.pack_into(e + "h", d, 344, source)
    return bytes(d) + data


# ---------------------------------------------------------------------- driver
@dataclass
class ScopeSettings:
    """Settings of an oscilloscope detector."""

    #: the serial link
    serial: SerialSettings = field(default_factory=SerialSettings)
    #: 'tektronix' (WFMOutpre? + CURVE?) or 'lecroy' (WF? with WAVEDESC)
    dialect: str = "tektronix"
    #: scope channels, one per observed patch, in observed-id order (1-based channel numbers)
    channels: tuple = (1,)
    #: path length (m) from emission to the scope's t = 0 (cables, trigger delay)
    trigger_offset_m: float = 0.0
    #: multiply volts by -1 (photodiodes often give negative pulses)
    invert: bool = False

    def validate(self) -> "ScopeSettings":
        self.serial.validate()
        if self.dialect not in ("tektronix", "lecroy"):
            raise AcquisitionSettingsError(f"ScopeSettings.dialect must be 'tektronix' or 'lecroy'; "
                                           f"got {self.dialect!r}.")
        chans = tuple(self.channels)
        if not chans or any(not isinstance(c, int) or not 1 <= c <= 8 for c in chans) or \
                len(set(chans)) != len(chans):
            raise AcquisitionSettingsError(f"ScopeSettings.channels must be distinct ints in 1..8; "
                                           f"got {self.channels!r}.")
        self.channels = chans
        if not math.isfinite(self.trigger_offset_m):
            raise AcquisitionSettingsError("ScopeSettings.trigger_offset_m must be finite metres.")
        return self


class Oscilloscope(PortDevice):
    """A SCPI oscilloscope as a STIR detector (one channel per observed patch)."""

    kind = "oscilloscope"

    def __init__(self, settings: ScopeSettings):
        self.settings = settings.validate()
        self.port = Port(settings.serial, device=f"oscilloscope ({settings.dialect}) on {settings.serial.port}")
        self.identity = ""
        self._grid: TimeGrid | None = None
        #: preamble fields the driver does not use (DPO/MDO/MSO: DOMAIN, WFMTYPE...), recorded
        self.preamble_extra: dict = {}

    def open(self) -> "Oscilloscope":
        self.port.open()
        self.identity = self.port.with_retries(lambda: self.port.query("*IDN?"), "*IDN?")
        if self.settings.dialect == "tektronix":
            for cmd in ("HEADER ON", "VERBOSE ON", "DATA:ENCDG RIBINARY", "DATA:WIDTH 2"):
                self.port.write(cmd)
        else:
            for cmd in ("CHDR OFF", "CFMT DEF9,WORD,BIN", "CORD LO"):
                self.port.write(cmd)
        return self

    @property
    def n_observed(self) -> int:
        return len(self.settings.channels)

    def _check_channel(self, channel: int, pre: dict) -> None:
        """The waveform must come from ``channel`` (a scope ignoring DATA:SOURCE is caught)."""
        p = self.port
        got = wfid_channel(pre.get("WFID"))
        said = f"WFID {pre.get('WFID')!r}"
        if got is None:
            line = p.query("DATA:SOURCE?")
            m = re.search(r"CH\s*(\d+)", line, re.IGNORECASE)
            got, said = (int(m.group(1)) if m else None), f"DATA:SOURCE? {line!r}"
        if got != channel:
            raise instrument_error(p.device, f"DATA:SOURCE CH{channel}",
                                   f"the scope sent a waveform of {'an unknown channel' if got is None else f'CH{got}'} "
                                   f"({said}) when CH{channel} was selected", said.encode(),
                                   fix="The scope ignored DATA:SOURCE; check its remote settings "
                                       "(channel on, not locked) and the --channels list.")

    def read_waveform(self, channel: int) -> Waveform:
        """One fresh acquisition of one channel (retried on timeouts and garbled replies)."""
        p = self.port
        if self.settings.dialect == "tektronix":
            def once() -> Waveform:
                # one compound line: two small writes in a row stall ~40 ms on TCP (Nagle)
                text = p.query(f"DATA:SOURCE CH{channel};:WFMOUTPRE?")
                try:
                    pre = parse_wfmoutpre(text)
                except InstrumentError as exc:
                    raise instrument_error(p.device, "WFMOUTPRE?", str(exc).rstrip("."),
                                           text.encode()) from None
                self._check_channel(channel, pre)
                payload = p.query_block("CURVE?", allowed_prefix=b":CURVE ",
                                        expect=int(pre["NR_PT"]) * int(pre["BYT_NR"]))
                try:
                    wf = tek_waveform(pre, payload)
                except InstrumentError as exc:
                    raise instrument_error(p.device, "CURVE?", str(exc).rstrip("."), payload) from None
                self.preamble_extra = preamble_extras(pre)
                return wf
            return p.with_retries(once, "CURVE?")
        cmd = f"C{channel}:WF? ALL"
        limit = None if self._grid is None else WAVEDESC_LEN + 65536 + 2 * self._grid.n_bins

        def once_lc() -> Waveform:
            payload = p.query_block(cmd, allowed_prefix=f"C{channel}:WF ALL,".encode(), limit=limit)
            try:
                wf = lecroy_waveform(payload)
            except InstrumentError as exc:
                raise instrument_error(p.device, cmd, str(exc).rstrip("."), payload) from None
            src = wf.header.get("WAVE_SOURCE")
            if src in (0, 1, 2, 3, 4, 5, 6, 7) and src != channel - 1:
                raise instrument_error(p.device, cmd, f"the scope sent a waveform of C{src + 1} "
                                       f"(WAVE_SOURCE {src}) when C{channel} was asked for",
                                       payload[:64], fix="Check the scope's remote settings.")
            return wf
        return p.with_retries(once_lc, cmd)

    def grid(self) -> TimeGrid:
        """The time grid (reads one waveform of the first channel if none was read yet)."""
        if self._grid is None:
            wf = self.read_waveform(self.settings.channels[0])
            self._grid = wf.grid(self.settings.trigger_offset_m)
        return self._grid

    def acquire(self, shots: int) -> np.ndarray:
        """Average ``shots`` acquisitions of every channel: ``(n_observed, n_bins)`` volts."""
        grid = self.grid()
        acc = np.zeros((self.n_observed, grid.n_bins))
        for _ in range(int(shots)):
            for j, ch in enumerate(self.settings.channels):
                wf = self.read_waveform(ch)
                g = wf.grid(self.settings.trigger_offset_m)
                if g.n_bins != grid.n_bins or not math.isclose(g.bin_width, grid.bin_width, rel_tol=1e-6) \
                        or not math.isclose(g.start, grid.start, rel_tol=0, abs_tol=1e-3 * grid.bin_width):
                    raise instrument_error(self.port.device, f"CH{ch} waveform",
                                           f"time axis changed during the capture: now {g}, was {grid}",
                                           fix="Do not change the timebase during a capture; start a "
                                               "new capture file.")
                acc[j] += wf.volts
        acc /= int(shots)
        return -acc if self.settings.invert else acc

    def describe(self) -> dict:
        s = self.settings
        return {"detector": "oscilloscope", "dialect": s.dialect, "identity": self.identity,
                "channels": list(s.channels), "trigger_offset_m": s.trigger_offset_m,
                "invert": s.invert, "unit": "V", "serial": s.serial.as_dict(),
                "preamble_extra": dict(self.preamble_extra)}
