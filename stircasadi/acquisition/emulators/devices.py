"""The three emulated instruments (scan controller, photon counter, oscilloscope) and the rig that
starts them on one shared bench (see the package docstring for the wire protocols and faults)."""
from __future__ import annotations

import numpy as np

from ...constants import C, m_to_ps
from ...timegrid import TimeGrid
from ..protocol import encode_block
from ..scope import lecroy_encode, tek_preamble_text
from .base import Bench, EmulatedDevice


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
