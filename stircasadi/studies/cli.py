"""``stircasadi study``: run a declarative study (a spec file or a built-in study).

    stircasadi study SPEC --out DIR [--size NAME] [--workers N | --serial | --scheduler ADDRESS]
                     [--retry-failed] [--fresh] [--keep-estimates] [--no-figures] [-q]
    stircasadi study --list          the built-in studies and their sizes
    stircasadi study --factors       every factor a spec may vary
    stircasadi study --report DIR    redraw the pictures and summary of a results folder
    stircasadi study SPEC --out DIR --cached-only   tables of the finished cells, computing nothing

Ctrl-C or a SIGTERM stops a study: finished cells stay in DIR/cells, partial tables are written,
and the same command resumes it.

Exit status: 0 when every cell ran (whatever the estimator concluded), 1 when some cells
failed or crashed (their errors are in the table), 2 for a bad spec or output folder,
130 when interrupted (rerun the same command to resume).
"""
from __future__ import annotations

import signal
import sys

from ..errors import StircasadiError, StudyError

__all__ = ["add_parsers", "cmd_study"]


def add_parsers(sub) -> None:
    """Register ``study`` on the ``stircasadi`` command's sub-parsers."""
    s = sub.add_parser("study", help="run a study (factors x repetitions) on Dask and tabulate it",
                       description=__doc__.split("\n\n")[0])
    s.add_argument("spec", nargs="?", help="a .toml/.yaml spec or a built-in study name (--list)")
    s.add_argument("--out", help="results folder (cells cache, tables, pictures)")
    s.add_argument("--size", default=None, help="a named size of the spec (e.g. smoke)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--workers", type=int, default=None, help="LocalCluster workers (default: one per core)")
    g.add_argument("--serial", action="store_true", help="run in this process, no Dask")
    g.add_argument("--scheduler", default=None, help="address of a running Dask scheduler")
    s.add_argument("--memory-limit", default=None,
                   help="memory of each local worker, e.g. 4GB (a cell beyond it is recorded as failed)")
    s.add_argument("--retry-failed", action="store_true", help="recompute cached cells that failed")
    s.add_argument("--fresh", action="store_true", help="ignore the cache, recompute every cell")
    s.add_argument("--keep-estimates", action="store_true", help="keep each estimate.json in its record")
    s.add_argument("--no-figures", action="store_true", help="tables only")
    s.add_argument("--cached-only", action="store_true",
                   help="compute nothing: tables and pictures of the cells already in DIR/cells")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.add_argument("--list", action="store_true", help="list the built-in studies")
    s.add_argument("--factors", action="store_true", help="describe every factor")
    s.add_argument("--report", metavar="DIR", default=None, help="redraw pictures and summary of DIR")
    s.set_defaults(func=cmd_study)


def _terminate(signum, frame):
    raise KeyboardInterrupt(f"signal {signum}")


def _list() -> int:
    from .spec import builtin_studies, load_study

    for name in builtin_studies():
        st = load_study(name)
        sizes = ", ".join(f"{k} ({len(load_study(name, k).cells())})" for k in st.sizes)
        print(f"{name:<18} {len(st.cells()):>4} cells  {st.description}  sizes: {sizes or '-'}")
    return 0


def _report(folder) -> int:
    from .plots import draw_all
    from .results import load_results, summary_markdown
    from ..io import atomic_write_text

    res = load_results(folder)
    res.figures = draw_all(res, res.out / "figures")
    atomic_write_text(res.out / "summary.md", summary_markdown(res))
    print(res.summary())
    for f in res.figures:
        print(f"  {f}")
    return 0


def cmd_study(args) -> int:
    from ..progress import set_verbosity
    from .runner import RunSettings, run_study
    from .factors import describe_factors

    if args.list:
        return _list()
    if args.factors:
        print(describe_factors())
        return 0
    if args.report:
        return _report(args.report)
    if not args.spec or not args.out:
        raise StudyError("stircasadi study needs SPEC and --out DIR (or --list / --factors / --report DIR).")
    set_verbosity(-1 if args.quiet else 0)
    settings = RunSettings(scheduler=args.scheduler, workers=0 if args.serial else args.workers,
                           retry_failed=args.retry_failed, fresh=args.fresh,
                           keep_estimates=args.keep_estimates, figures=not args.no_figures,
                           cached_only=args.cached_only, memory_limit=args.memory_limit)
    signal.signal(signal.SIGTERM, _terminate)  # a kill stops the study like Ctrl-C: cache kept
    try:
        res = run_study(args.spec, args.out, size=args.size, settings=settings)
    except KeyboardInterrupt:
        print(f"stircasadi study: interrupted; finished cells are kept in {args.out}/cells. Run the "
              "same command again to resume.", file=sys.stderr)
        return 130
    except StircasadiError:
        raise
    print(res.summary())
    for f in res.figures:
        print(f"  {f}")
    bad = res.cells["status"].isin(["failed", "crashed"]).sum() if len(res.cells) else 0
    if bad:
        print(f"{bad} cell(s) failed or crashed; their errors are in {args.out}/cells.parquet "
              "(columns status, stage, error_type, error).", file=sys.stderr)
    return 1 if bad else 0
