"""The ``stircasadi`` command: the parser, the verbosity options and the one error policy.

    stircasadi [-q|-v] run [PROBLEM] [--out DIR] [--seed N]
    stircasadi [-q|-v] simulate PROBLEM --out capture.h5 [--noise none] [--seed N] [--bounces K|all]
    stircasadi [-q|-v] estimate CAPTURE --out estimate.json [--hidden N] [--brdf lambertian|phong]
    stircasadi plot [CAPTURE] [ESTIMATE] [--out DIR]
    stircasadi problems
    stircasadi import | export | acquire ...                 (stircasadi.acquisition.cli)
    stircasadi relight | separate | segment | replace | deconvolve ...   (stircasadi.apps.cli)

Exit status: 0 done (verdict OK), 3 the estimate's self-checks failed (UNRELIABLE: written, with
the reasons), 2 a bad argument or input, an unwritable output or a failed solver (one line on
standard error, nothing overwritten), 1 an unexpected internal error (one line; ``-v`` shows the
traceback), 130 interrupted.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import time

from .. import __version__
from ..errors import StircasadiError
from ..progress import get_logger, set_verbosity
from . import args as A

__all__ = ["build_parser", "main", "EXIT_OK", "EXIT_ERROR", "EXIT_UNRELIABLE", "EXIT_INTERNAL"]

EXIT_OK, EXIT_INTERNAL, EXIT_ERROR, EXIT_UNRELIABLE, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
log = get_logger(__name__)

#: modules that register more sub-commands through ``add_parsers(subparsers)``
EXTENSIONS = ("stircasadi.acquisition.cli", "stircasadi.apps.cli", "stircasadi.studies.cli")


def _verbosity(p: argparse.ArgumentParser, top: bool) -> None:
    """-q/-v on the top level and (without overriding it) on each of our sub-commands."""
    g = p.add_mutually_exclusive_group()
    kw = {} if top else {"default": argparse.SUPPRESS}
    g.add_argument("-q", "--quiet", dest="_quiet", action="store_true",
                   help="warnings and results only: no progress bars, no stage messages",
                   **({"default": False} if top else kw))
    g.add_argument("-v", "--verbose", dest="_verbose", action="count",
                   help="more detail: -v debug messages, -vv also tracebacks of internal errors",
                   **({"default": 0} if top else kw))


def build_parser() -> argparse.ArgumentParser:
    from . import commands, plot, run

    p = argparse.ArgumentParser(prog="stircasadi", formatter_class=A.Formatter,
                                description="Inverse transient light transport: simulate a scene's "
                                "space-time impulse response (STIR), estimate its geometry and "
                                "reflectance, and check the estimate against the data.",
                                epilog="Exit status: 0 OK, 3 UNRELIABLE (estimate written, checks "
                                       "failed), 2 bad input or failed solve, 1 internal error.")
    p.add_argument("--version", action="version", version=f"stircasadi {__version__}")
    _verbosity(p, top=True)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for mod in (run, commands, plot):
        for sp in mod.add_parsers(sub):
            _verbosity(sp, top=False)
    for name in EXTENSIONS:
        _extend(sub, name)
    return p


#: extension modules skipped by the last ``build_parser`` (absent, or an optional dependency missing)
UNAVAILABLE: dict = {}


def _extend(sub, module: str) -> None:
    """Register the sub-commands of ``module`` (skipped, noted in ``UNAVAILABLE`` and reported
    by ``-v``, when it is absent or lacks an optional dependency)."""
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        UNAVAILABLE[module] = str(exc)
        return
    mod.add_parsers(sub)


def _exit_code(exc: SystemExit) -> int:
    if exc.code is None:
        return EXIT_OK
    return exc.code if isinstance(exc.code, int) else EXIT_ERROR


def main(argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    t0 = time.perf_counter()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # usage errors (argparse printed them), --help, --version
        return _exit_code(exc)
    args._argv = list(sys.argv[1:] if argv is None else argv)
    args._t0 = t0
    verbose = int(getattr(args, "_verbose", 0) or 0)
    set_verbosity(-1 if getattr(args, "_quiet", False) else min(verbose, 1))
    for module, why in UNAVAILABLE.items():
        log.debug(f"commands of {module} not available: {why}")
    name = f"stircasadi {args.command}"
    try:
        return int(args.func(args) or 0)
    except StircasadiError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f"{name}: interrupted; files already written are complete, nothing is half-written.",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    except MemoryError:
        print(f"{name}: out of memory. Try a smaller problem or a machine with more memory.",
              file=sys.stderr)
        return EXIT_ERROR
    except OSError as exc:
        print(f"{name}: {exc.strerror or exc}" + (f": {exc.filename}" if exc.filename else "")
              + ". Nothing at that path was changed.", file=sys.stderr)
        return EXIT_ERROR
    except Exception as exc:  # noqa: BLE001 -- the one place that turns a bug into one line
        if verbose >= 2:
            import traceback

            traceback.print_exc()
        print(f"{name}: internal error ({type(exc).__name__}: {exc}). Files already written are "
              "complete. Rerun with -vv for the traceback and report it.", file=sys.stderr)
        return EXIT_INTERNAL
