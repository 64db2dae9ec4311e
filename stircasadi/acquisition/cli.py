"""The ``import``, ``export`` and ``acquire`` subcommands (registered by ``stircasadi.cli`` via ``add_parsers``).

``stircasadi import FILE [--format F] --out capture.h5`` reads a recording (format detected when
omitted) and writes a Capture; ``stircasadi export CAPTURE --format ytal --out file.hdf5`` writes
a Capture in another tool's format. ``stircasadi acquire`` drives a scan controller and a
detector over serial ports or VISA resources (``--resource TCPIP::...``) patch by patch; every
completed row is saved before the next aim, Ctrl-C / SIGTERM end with one line saying how many
rows are safe and the exact ``--resume`` command. With ``--emulate PROBLEM`` it first starts
emulators backed by the problem's forward model (serial ptys, or with ``--emulate-transport
visa`` a loopback LAN scope) and captures through the same drivers: the end-to-end dry run of a rig.
"""
from __future__ import annotations

import argparse
import shlex
import signal
import sys

import numpy as np

from ..errors import StircasadiError
from ..progress import get_logger, progress, set_verbosity

log = get_logger(__name__)


def forward_source(problem: str | None):
    """``(trace_for, n_patches, n_observed, grid, transient)`` from a problem's forward model."""
    from ..problem import load_problem
    from ..transport import simulate

    mod = load_problem(problem)
    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    tr = simulate(scene, grid, sensor=sensor)
    stir = np.asarray(tr.stir, dtype=float)
    return (lambda i: stir[i]), stir.shape[0], stir.shape[1], tr.grid, tr


# ---------------------------------------------------------------------- argument types
def _number(kind, low, strict: bool, what: str):
    def parse(text: str):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be {what}; got {text!r}") from None
        if not np.isfinite(v) or (v <= low if strict else v < low):
            raise argparse.ArgumentTypeError(f"must be {what}; got {text!r}")
        return v
    return parse


positive_int = _number(int, 0, True, "an integer >= 1")
nonneg_int = _number(int, 0, False, "an integer >= 0")
positive_float = _number(float, 0.0, True, "a number > 0")


def _ids(text: str) -> list[int]:
    try:
        ids = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be comma-separated integers such as 0,1,2; got {text!r}") from None
    if not ids or min(ids) < 0:
        raise argparse.ArgumentTypeError(f"must be comma-separated integers >= 0; got {text!r}")
    return ids


def fault_spec(text: str):
    """``KIND:COMMAND[:NTH]`` -> ``Fault`` (e.g. ``disconnect:ACQ:2``)."""
    from .emulators import FAULT_KINDS, Fault

    parts = text.split(":")
    if len(parts) not in (2, 3) or parts[0] not in FAULT_KINDS or not parts[1]:
        raise argparse.ArgumentTypeError(f"must be KIND:COMMAND[:NTH] with KIND one of {', '.join(FAULT_KINDS)}, "
                                         f"e.g. disconnect:ACQ:2; got {text!r}")
    nth = 1
    if len(parts) == 3:
        nth = positive_int(parts[2])
    return Fault(parts[0], parts[1], nth=nth)


# ---------------------------------------------------------------------- import / export
def _run_import(args) -> int:
    from ..io import check_output
    from .importers import detect_format, import_file

    out = check_output(args.out, inputs=[args.file], what="capture", suffixes=(".h5", ".hdf5"))
    opts = {"time_unit": args.time_unit, "legs_included": False if args.rectified else None}
    with progress(total=2, desc="import", unit="step") as bar:
        fmt = args.format or detect_format(args.file)
        cap = import_file(args.file, fmt, **opts)
        bar.update(1)
        cap.provenance.setdefault("source_format", fmt)
        cap.write(out, inputs=[args.file])
        bar.update(1)
    data = cap.stir if cap.stir is not None else cap.traces
    print(f"import: {args.file} ({fmt}) -> {out}: "
          f"{'stir' if cap.stir is not None else 'traces'} {data.shape}, {cap.grid}")
    return 0


def _run_export(args) -> int:
    from ..capture import Capture
    from ..io import check_output
    from .importers import export_file

    out = check_output(args.out, inputs=[args.capture], what=args.format)
    cap = Capture.read(args.capture)
    export_file(cap, args.format, out, inputs=[args.capture])
    print(f"export: {args.capture} -> {out} ({args.format})")
    return 0


# ---------------------------------------------------------------------- acquire
def _resume_command(argv) -> str:
    words = [w for w in argv if w != "--resume"]
    return shlex.join(["stircasadi"] + words + ["--resume"])


def _raise_interrupted(signum, frame):
    from .session import Interrupted
    raise Interrupted(signal.Signals(signum).name)


def _link(args, port: str):
    from .serialio import SerialSettings

    return SerialSettings(port=port, baudrate=args.baud, timeout_s=args.timeout, retries=args.retries,
                          visa_library=args.visa_library)


def _acquire(args) -> int:
    from .counter import CounterSettings, HistogramCounter
    from .emulators import EmulatedRig
    from .scan import ScanController, ScanSettings
    from .scope import Oscilloscope, ScopeSettings
    from .session import acquire

    from ..io import check_output

    check_output(args.out, what="capture")   # before any emulator, instrument or forward model
    rig = None
    scan_port, det_port = args.scan_port, args.resource or args.detector_port
    channels = args.channels
    extra = {}
    try:
        if args.emulate:
            if args.emulate_transport == "visa" and args.detector == "counter":
                raise StircasadiError("--emulate-transport visa emulates a LAN oscilloscope; use "
                                      "--detector tektronix or lecroy.")
            trace_for, n_patch, n_obs, grid, _ = forward_source(args.emulate)
            peak = max(float(np.max(trace_for(i))) for i in range(n_patch))
            if not peak > 0:
                raise StircasadiError(f"problem {args.emulate!r} gives an all-zero STIR; nothing to emulate.")
            kw = ({"gain": args.emulate_photons / (peak * args.shots), "sync_rate_hz": args.emulate_sync_hz}
                  if args.detector == "counter" else {"volts_per_unit": 0.5 / peak, "noise_v": 1e-3})
            rig = EmulatedRig(trace_for, n_patch, n_obs, grid, detector=args.detector,
                              detector_faults=list(args.emulate_fault or []), seed=args.seed,
                              transport="tcp" if args.emulate_transport == "visa" else "pty", **kw).start()
            scan_port, det_port = rig.scan.port, rig.detector.port
            if channels is None:
                channels = list(range(n_obs)) if args.detector == "counter" else list(range(1, n_obs + 1))
            extra = {"emulated_problem": args.emulate, "emulator": kw,
                     "emulated_transport": args.emulate_transport}
        if not scan_port or not det_port:
            raise StircasadiError("acquire needs --scan-port and --detector-port (e.g. /dev/ttyUSB0) or "
                                  "--resource (a VISA address such as TCPIP::192.168.1.5::INSTR), or "
                                  "--emulate PROBLEM for a dry run on emulators.")
        scan = ScanController(ScanSettings(_link(args, scan_port)))
        if args.detector == "counter":
            det = HistogramCounter(CounterSettings(_link(args, det_port), channels=tuple(channels or [0]),
                                                   sync_offset_m=args.time_offset_m))
        else:
            det = Oscilloscope(ScopeSettings(_link(args, det_port), dialect=args.detector,
                                             channels=tuple(channels or [1]),
                                             trigger_offset_m=args.time_offset_m))
        with scan, det, progress(total=len(args.patches) if args.patches else scan.n_patches,
                                 desc="acquire", unit="patch") as bar:
            def report(done, total, patch, elapsed):
                bar.n = done
                bar.set_postfix_str(f"patch {patch}")
                log.info("acquire: patch %d done, %d/%d (%.0f %%), %.2f s/patch", patch, done, total,
                         100 * done / total, elapsed / max(done, 1))
            out = acquire(scan, det, args.out, shots=args.shots, patches=args.patches,
                          resume=args.resume, legs_included=not args.rectified, progress=report,
                          extra_provenance=extra)
        print(f"acquire: wrote {out}")
        return 0
    finally:
        if rig is not None:
            rig.stop()


def _run_acquire(args) -> int:
    set_verbosity(-1 if args.quiet else (1 if args.verbose else 0))
    argv = getattr(args, "argv", None) or sys.argv[1:]
    handlers = {}
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            handlers[name] = signal.signal(getattr(signal, name), _raise_interrupted)
    if hasattr(signal, "SIGXFSZ"):  # a file-size limit gives a clear error, not a core dump
        handlers["SIGXFSZ"] = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        return _acquire(args)
    except (KeyboardInterrupt, StircasadiError, OSError) as exc:
        safe, total, journal = (getattr(exc, k, None) for k in ("rows_safe", "rows_total", "journal"))
        if isinstance(exc, KeyboardInterrupt):
            what = f"interrupted by {getattr(exc, 'signame', 'SIGINT (Ctrl-C)')}"
        else:
            what = "error: " + " ".join(str(exc).split())
        if safe is not None and journal is not None:
            print(f"acquire: {what} -- {safe} of {total} rows are safe in {journal}; resume with: "
                  f"{_resume_command(argv)}", file=sys.stderr)
        else:
            print(f"acquire: {what}", file=sys.stderr)
        return 130 if isinstance(exc, KeyboardInterrupt) else 2
    finally:
        for name, h in handlers.items():
            signal.signal(getattr(signal, name), h)


def _guard(fn):
    def run(args) -> int:
        try:
            return fn(args)
        except StircasadiError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    return run


def add_parsers(subparsers) -> None:
    """Register ``import``, ``export`` and ``acquire`` on an argparse ``subparsers`` object."""
    from .emulators import FAULT_KINDS
    from .importers import FORMATS, exporters

    fmt_help = "; ".join(f"{k}: {v.description}" for k, v in FORMATS.items())
    kw = {"formatter_class": argparse.ArgumentDefaultsHelpFormatter}
    p = subparsers.add_parser("import", help="convert a recording (PTU, y-tal, .mat, CSV...) to a Capture",
                              description="Formats: " + fmt_help, **kw)
    p.add_argument("file", help="the recording (a file, or a folder for ccsocr/general-nlos)")
    p.add_argument("--format", choices=list(FORMATS), default=None,
                   help="file format (detected from the file when omitted)")
    p.add_argument("--out", required=True, help="Capture HDF5 file to write (.h5); never the input")
    p.add_argument("--time-unit", default=None,
                   help="time unit of CSV/NPZ files that do not state it (s, ns, ps, m, mm)")
    p.add_argument("--rectified", action="store_true",
                   help="CSV/NPZ/PTU times exclude the source and camera legs (legs_included=False)")
    p.set_defaults(func=_guard(_run_import))

    e = subparsers.add_parser("export", help="write a Capture in another tool's format (y-tal HDF5)", **kw)
    e.add_argument("capture", help="the Capture HDF5 file")
    e.add_argument("--format", choices=exporters(), required=True, help="format to write")
    e.add_argument("--out", required=True, help="file to write (e.g. scan.hdf5); never the input")
    e.set_defaults(func=_guard(_run_export))

    a = subparsers.add_parser("acquire", help="capture a STIR patch by patch from serial or VISA instruments",
                              **kw)
    a.add_argument("--out", required=True,
                   help="Capture HDF5 file (rows go to <out>.journal until every patch is in)")
    a.add_argument("--scan-port", help="serial port (or VISA resource) of the galvo scan controller")
    a.add_argument("--detector", choices=["counter", "tektronix", "lecroy"], default="counter",
                   help="detector kind: TCSPC histogramming counter or SCPI oscilloscope dialect")
    a.add_argument("--detector-port", help="serial port of the counter or oscilloscope (e.g. /dev/ttyUSB0)")
    a.add_argument("--resource", help="VISA resource of the detector instead of --detector-port, e.g. "
                                      "TCPIP::192.168.1.5::INSTR or USB0::0x0699::0x0401::C0001::INSTR")
    a.add_argument("--visa-library", default="@py", help="pyvisa backend ('@py' pyvisa-py; '' system VISA)")
    a.add_argument("--channels", type=_ids, default=None,
                   help="detector channels, one per observed patch (counter 0,1,2; scopes 1,2,3); "
                        "default: all of an emulated rig, else the first")
    a.add_argument("--patches", type=_ids, default=None,
                   help="illumination patch ids in scan order (default: all of the controller's table)")
    a.add_argument("--shots", type=positive_int, default=1000,
                   help="pulses averaged (scope) or sync periods accumulated (counter) per patch")
    a.add_argument("--baud", type=int, default=115200, help="serial line rate, bits per second")
    a.add_argument("--timeout", type=positive_float, default=2.0,
                   help="seconds allowed for a short reply (longer replies get more)")
    a.add_argument("--retries", type=nonneg_int, default=2,
                   help="times a command is re-sent after a timeout or a garbled reply")
    a.add_argument("--time-offset-m", type=float, default=0.0,
                   help="path length from emission to the detector's t=0 (cables, trigger), metres")
    a.add_argument("--rectified", action="store_true", help="times exclude the source/camera legs")
    a.add_argument("--resume", action="store_true", help="complete an interrupted capture from its journal")
    a.add_argument("--quiet", action="store_true", help="warnings only, no progress bar")
    a.add_argument("--verbose", action="store_true", help="also log every saved row with its CRC-32")
    a.add_argument("--emulate", metavar="PROBLEM",
                   help="dry run: emulated rig backed by PROBLEM's forward model")
    a.add_argument("--emulate-transport", choices=["serial", "visa"], default="serial",
                   help="emulated detector link: serial ptys, or a LAN scope on a loopback VISA socket")
    a.add_argument("--emulate-photons", type=positive_float, default=2e4,
                   help="emulated counter: expected counts in the brightest bin")
    a.add_argument("--emulate-sync-hz", type=positive_float, default=1e8,
                   help="emulated counter: laser repetition rate (sets the time one patch takes)")
    a.add_argument("--emulate-fault", action="append", type=fault_spec, metavar="KIND:COMMAND[:NTH]",
                   help=f"inject a fault in the emulated detector ({', '.join(FAULT_KINDS)}), "
                        "e.g. disconnect:ACQ:2")
    a.add_argument("--seed", type=nonneg_int, default=0, help="emulator noise seed")
    a.set_defaults(func=_run_acquire)


def main(argv=None) -> int:
    """Stand-alone entry (``python -m stircasadi.acquisition.cli``)."""
    parser = argparse.ArgumentParser(prog="stircasadi")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parser.parse_args(argv)
    args.argv = argv
    return args.func(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
