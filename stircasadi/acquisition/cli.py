"""The ``import`` and ``acquire`` subcommands (registered by ``stircasadi.cli`` via ``add_parsers``).

``stircasadi import FILE [--format F] --out capture.h5`` reads a recording (format detected when
omitted) and writes a Capture. ``stircasadi acquire`` drives a scan controller and a detector
over serial ports patch by patch (``--resume`` completes an interrupted capture); with
``--emulate PROBLEM`` it first starts pty emulators backed by the problem's forward model and
captures through the same drivers, which is the end-to-end dry run of a rig.
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from ..errors import StircasadiError


def forward_source(problem: str | None):
    """``(trace_for, n_patches, n_observed, grid, transient)`` from a problem's forward model."""
    from ..problem import load_problem
    from ..transport import simulate

    mod = load_problem(problem)
    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    tr = simulate(scene, grid, sensor=sensor)
    stir = np.asarray(tr.stir, dtype=float)
    return (lambda i: stir[i]), stir.shape[0], stir.shape[1], tr.grid, tr


def _ids(text: str | None, what: str):
    if text is None:
        return None
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise StircasadiError(f"--{what} must be comma-separated integers such as 0,1,2; got {text!r}.") from None


def _run_import(args) -> int:
    from .importers import detect_format, import_file

    opts = {}
    if args.time_unit:
        opts["time_unit"] = args.time_unit
    if args.rectified:
        opts["legs_included"] = False
    fmt = args.format or detect_format(args.file)
    cap = import_file(args.file, fmt, **opts)
    cap.provenance.setdefault("source_format", fmt)
    out = cap.write(args.out)
    data = cap.stir if cap.stir is not None else cap.traces
    print(f"import: {args.file} ({fmt}) -> {out}: "
          f"{'stir' if cap.stir is not None else 'traces'} {data.shape}, {cap.grid}")
    return 0


def _run_acquire(args) -> int:
    from .counter import CounterSettings, HistogramCounter
    from .emulators import EmulatedRig, Fault
    from .scan import ScanController, ScanSettings
    from .scope import Oscilloscope, ScopeSettings
    from .serialio import SerialSettings
    from .session import acquire, progress_printer

    rig = None
    scan_port, det_port = args.scan_port, args.detector_port
    channels = _ids(args.channels, "channels")
    extra = {}
    try:
        if args.emulate:
            trace_for, n_patch, n_obs, grid, _ = forward_source(args.emulate)
            faults = []
            for spec in args.emulate_fault or []:
                kind, cmd, nth = (spec.split(":") + ["1"])[:3]
                faults.append(Fault(kind, cmd, nth=int(nth)))
            peak = max(float(np.max(trace_for(i))) for i in range(n_patch))
            kw = ({"gain": args.emulate_photons / (peak * args.shots), "sync_rate_hz": 1e8}
                  if args.detector == "counter" else {"volts_per_unit": 0.5 / peak, "noise_v": 1e-3})
            rig = EmulatedRig(trace_for, n_patch, n_obs, grid, detector=args.detector,
                              detector_faults=faults, seed=args.seed, **kw).start()
            scan_port, det_port = rig.scan.port, rig.detector.port
            if channels is None:
                channels = list(range(n_obs)) if args.detector == "counter" else list(range(1, n_obs + 1))
            extra = {"emulated_problem": args.emulate, "emulator": kw}
        if not scan_port or not det_port:
            raise StircasadiError("acquire needs --scan-port and --detector-port (e.g. /dev/ttyUSB0), "
                                  "or --emulate PROBLEM for a dry run on emulators.")

        def link(port):
            return SerialSettings(port=port, baudrate=args.baud, timeout_s=args.timeout,
                                  retries=args.retries)
        scan = ScanController(ScanSettings(link(scan_port)))
        if args.detector == "counter":
            det = HistogramCounter(CounterSettings(link(det_port), channels=tuple(channels or [0]),
                                                   sync_offset_m=args.time_offset_m))
        else:
            det = Oscilloscope(ScopeSettings(link(det_port), dialect=args.detector,
                                             channels=tuple(channels or [1]),
                                             trigger_offset_m=args.time_offset_m))
        with scan, det:
            out = acquire(scan, det, args.out, shots=args.shots, patches=_ids(args.patches, "patches"),
                          resume=args.resume, legs_included=not args.rectified,
                          progress=None if args.quiet else progress_printer(),
                          extra_provenance=extra)
        print(f"acquire: wrote {out}")
        return 0
    finally:
        if rig is not None:
            rig.stop()


def _guard(fn):
    def run(args) -> int:
        try:
            return fn(args)
        except StircasadiError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    return run


def add_parsers(subparsers) -> None:
    """Register ``import`` and ``acquire`` on an argparse ``subparsers`` object."""
    from .importers import FORMATS

    p = subparsers.add_parser("import", help="convert a recording (PTU, y-tal, .mat, CSV...) to a Capture",
                              description="Formats: " + "; ".join(f"{k}: {v[1]}" for k, v in FORMATS.items()))
    p.add_argument("file", help="the recording")
    p.add_argument("--format", choices=list(FORMATS), default=None,
                   help="file format (detected from the file when omitted)")
    p.add_argument("--out", required=True, help="Capture HDF5 file to write")
    p.add_argument("--time-unit", default=None, help="time unit of CSV/NPZ files that do not state it")
    p.add_argument("--rectified", action="store_true",
                   help="CSV/NPZ/PTU times exclude the source and camera legs (legs_included=False)")
    p.set_defaults(func=_guard(_run_import))

    a = subparsers.add_parser("acquire", help="capture a STIR patch by patch from serial instruments")
    a.add_argument("--out", required=True, help="Capture HDF5 file (written as <out>.partial until complete)")
    a.add_argument("--scan-port", help="serial port of the galvo scan controller")
    a.add_argument("--detector", choices=["counter", "tektronix", "lecroy"], default="counter")
    a.add_argument("--detector-port", help="serial port of the counter or oscilloscope")
    a.add_argument("--channels", help="detector channels, one per observed patch (e.g. 0,1,2; scopes 1,2,3)")
    a.add_argument("--patches", help="illumination patch ids in scan order (default: all)")
    a.add_argument("--shots", type=int, default=1000,
                   help="pulses averaged (scope) or sync periods accumulated (counter) per patch")
    a.add_argument("--baud", type=int, default=115200)
    a.add_argument("--timeout", type=float, default=2.0, help="seconds for a short reply (grows with length)")
    a.add_argument("--retries", type=int, default=2)
    a.add_argument("--time-offset-m", type=float, default=0.0,
                   help="path length from emission to the detector's t=0 (cables, trigger), metres")
    a.add_argument("--rectified", action="store_true", help="times exclude the source/camera legs")
    a.add_argument("--resume", action="store_true", help="complete an interrupted capture")
    a.add_argument("--quiet", action="store_true", help="no progress lines")
    a.add_argument("--emulate", metavar="PROBLEM", help="dry run: emulated rig backed by PROBLEM's forward model")
    a.add_argument("--emulate-photons", type=float, default=2e4,
                   help="emulated counter: expected counts in the brightest bin")
    a.add_argument("--emulate-fault", action="append", metavar="KIND:COMMAND[:NTH]",
                   help="inject a fault in the emulated detector, e.g. disconnect:ACQ:2")
    a.add_argument("--seed", type=int, default=0, help="emulator noise seed")
    a.set_defaults(func=_guard(_run_acquire))


def main(argv=None) -> int:
    """Stand-alone entry (``python -m stircasadi.acquisition.cli``) until the main CLI calls us."""
    parser = argparse.ArgumentParser(prog="stircasadi")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
