"""``stircasadi run``: simulate a problem, estimate it blind, compare with the truth, draw it.

    stircasadi run [PROBLEM] [--out DIR] [--seed N] [--renderer auto|pyvista|matplotlib]

Prints the problem, the simulation, one table (one row per patch, err/σ against the truth,
``report.table``), what the estimate found (``summary``), the timings of every stage once, and
the files written. Writes into DIR: capture.h5 (the simulated capture, with its truth),
estimate.json (the estimate, schema docs/estimate-json.md), report.json (this run: problem,
seed, simulation metadata, timings, files, the comparison with the truth — nothing of
estimate.json repeated), scene.png and profiles.png. The estimator is given the capture without
its truth group. The folder and every file are checked before the simulation starts.
"""
from __future__ import annotations

import argparse
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import OutputError, StircasadiError
from ..problem import DEFAULT_PROBLEM
from ..progress import get_logger
from . import args as A
from .commands import describe_simulation, known_geometry, script_inputs, simulate_problem
from .plot import PICTURES, make_pictures, model_from_fit
from .summary import estimate_stage_times, print_summary, timing_line

__all__ = ["add_parsers", "cmd_run", "RUN_FILES"]

log = get_logger(__name__)
RUN_FILES = ("capture.h5", "estimate.json", "report.json") + PICTURES


def check_run_folder(out, inputs) -> Path:
    """The output folder and each file it will hold, checked before any work."""
    from ..io import check_output

    folder = check_output(out, inputs=inputs, what="output", folder=True)
    if folder.exists():
        for name in RUN_FILES:
            check_output(folder / name, inputs=inputs, what="output")
    return folder


def _comparison(d: dict, truth: dict) -> dict:
    """What the truth says of the estimate (report.json): RMSE, err/σ statistics, worst number."""
    from ..report import compare, position_rmse

    allrows = compare(d, truth)

    def estimated(r):  # inputs (std 0: known points, calibrated normals, declared areas) are left out
        sd = np.atleast_1d(np.asarray(r["std"] if r["std"] is not None else np.nan, float))
        return r["z"] is not None and np.all(np.isfinite(sd)) and np.any(sd > 0)
    rows = [r for r in allrows if r["quantity"] != "match" and estimated(r)]
    z = np.array([r["z"] for r in rows], float)
    fin = z[np.isfinite(z)]
    out = {"n_numbers": len(rows), "unmatched_patches": sum(r["quantity"] == "match" for r in allrows)}
    try:
        out["visible_position_rmse_m"] = position_rmse(d, truth)[0]
    except (ValueError, IndexError):
        pass
    if len(z):
        k = int(np.argmax(np.where(np.isfinite(z), z, 1e300)))
        out.update({"fraction_within_1_sigma": float(np.mean(z <= 1)),
                    "fraction_within_2_sigma": float(np.mean(z <= 2)),
                    "max_err_over_sigma": float(z[k]) if np.isfinite(z[k]) else None,
                    "worst": {"id": rows[k]["id"], "quantity": rows[k]["quantity"],
                              "error": rows[k]["error"], "std": rows[k]["std"]},
                    "n_beyond_3_sigma": int(np.sum(z > 3)), "median_err_over_sigma":
                        float(np.median(fin)) if fin.size else None})
    return out


def cmd_run(args) -> int:
    from ..io import atomic_write_text
    from ..problem import describe, load_problem, problem_name
    from ..report import dumps, match, table
    from ..viz import patch_names
    from .main import EXIT_UNRELIABLE

    t_start = getattr(args, "_t0", None) or time.perf_counter()
    mod = load_problem(args.problem)
    inputs = script_inputs(args.problem)
    folder = check_run_folder(args.out, inputs)
    name = problem_name(mod)
    from .. import pipeline, transport  # noqa: F401 -- CasADi, SciPy: imported once, timed here
    timings: dict = {"start-up": time.perf_counter() - t_start}  # parsing, checks, imports
    print(f"stircasadi {__version__} — problem '{name}': {describe(mod)}")
    t = time.perf_counter()
    mod, scene, tr, cap = simulate_problem(mod, seed=args.seed)
    timings["simulate"] = time.perf_counter() - t
    print(scene.describe())
    print(describe_simulation(tr, cap))
    stage = known_geometry(mod, scene, cap)
    if stage:
        print(stage)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"Cannot create the output folder {folder}: {exc.strerror or exc}.") from None
    t = time.perf_counter()
    cap.write(folder / "capture.h5", inputs=inputs)
    timings["write capture"] = time.perf_counter() - t
    files = {"capture": "capture.h5"}
    report = {"format": "stircasadi.run-report", "version": 1, "producer": f"stircasadi {__version__}",
              "problem": name, "description": describe(mod), "seed": args.seed,
              "command": " ".join(["stircasadi"] + list(getattr(args, "_argv", []))),
              "simulation": {k: v for k, v in tr.metadata.items() if not k.startswith("_")},
              "blind": "the estimator was given the capture without its truth group"}
    opts = dict(getattr(mod, "ESTIMATE", {}) or {})
    truth, cap.truth = cap.truth, None
    print("estimating blind (the estimator does not see the truth) ...", flush=True)
    t = time.perf_counter()
    try:
        from ..pipeline import estimate_capture

        limit = getattr(args, "time_limit", "default")   # absent: not given on the command line
        limit = opts.get("time_limit", A.TIME_LIMIT_DEFAULT) if limit == "default" else limit
        res = estimate_capture(cap, brdf=opts.get("brdf", "lambertian"), hidden=opts.get("hidden"),
                               time_limit=limit)
    except StircasadiError as exc:
        timings["estimate"] = time.perf_counter() - t
        report.update({"timings_s": timings, "files": files, "error": str(exc)})
        atomic_write_text(folder / "report.json", dumps(report))
        raise StircasadiError(f"the estimate failed ({exc}); {folder / 'capture.h5'} and "
                              f"{folder / 'report.json'} were written.") from exc
    finally:
        cap.truth = truth
    t_est = time.perf_counter() - t
    d = res.to_json_dict()
    t = time.perf_counter()
    atomic_write_text(folder / "estimate.json", dumps(d))
    files["estimate"] = "estimate.json"
    t_write = time.perf_counter() - t
    scene_names = [p.name for p in scene.patches]
    scene_names = scene_names if any(scene_names) else None
    names = patch_names(d, scene_names, match(d, truth)) if truth is not None else patch_names(d)
    print(table(d, truth, names=scene_names))
    print_summary(d, names)
    t = time.perf_counter()
    try:
        model = model_from_fit(res, cap)
    except Exception as exc:  # noqa: BLE001 -- a missing curve never costs the pictures
        log.warning(f"no model curve on the profiles: {type(exc).__name__}: {exc}")
        model = None
    pics = make_pictures(folder, cap, d, truth, model, "model (joint fit)", names, name, args.renderer)
    t_pics = time.perf_counter() - t
    for pic, (path, _, note) in pics.items():
        if path is not None:
            files[pic.split(".")[0]] = pic
        else:
            print(f"{pic} {note}", file=sys.stderr)
    timings["estimate"] = (t_est, estimate_stage_times(d))
    timings["write results"] = t_write
    timings["pictures"] = (t_pics, {p.split(".")[0]: s for p, (_, s, _) in pics.items()})
    timings["total"] = time.perf_counter() - t_start
    files["report"] = "report.json"
    report.update({"timings_s": {k: ({"total": v[0], **v[1]} if isinstance(v, tuple) else v)
                                 for k, v in timings.items()},
                   "files": files, "pictures": {p: note for p, (_, _, note) in pics.items()}})
    if truth is not None:
        report["truth_comparison"] = _comparison(d, truth)
    atomic_write_text(folder / "report.json", dumps(report))
    print(timing_line(timings))
    sizes = ", ".join(f"{f} ({(folder / f).stat().st_size / 1e3:.0f} kB)" for f in files.values())
    print(f"wrote {folder}/: {sizes}")
    return 0 if d.get("success") else EXIT_UNRELIABLE


def add_parsers(sub) -> list:
    r = sub.add_parser("run", formatter_class=A.Formatter,
                       help="simulate a problem, estimate it blind, print a table against the truth",
                       description=textwrap.fill(" ".join(__doc__.split("\n\n", 2)[2].replace("``", "")
                                                           .split()), 90) if __doc__ else None)
    r.add_argument("problem", nargs="?", default=DEFAULT_PROBLEM, type=A.problem,
                   help="problem name (see 'stircasadi problems') or path to a problem script")
    r.add_argument("--out", default="runs/latest",
                   help="folder for capture.h5, estimate.json, report.json, scene.png, profiles.png "
                        "(created if missing; files in it are replaced)")
    r.add_argument("--seed", type=A.seed, default=0, help=f"noise seed, 0 to {A.SEED_MAX}")
    r.add_argument("--renderer", choices=["auto", "pyvista", "matplotlib"], default="auto",
                   help="3-D renderer of scene.png: pyvista when installed, else matplotlib")
    r.add_argument("--time-limit", type=A.time_limit, default=argparse.SUPPRESS, metavar="SECONDS",
                   help="wall-clock limit of the estimate (default: the problem's ESTIMATE['time_limit'], "
                        f"else {A.TIME_LIMIT_DEFAULT:g} s); where it runs out the result is the last "
                        "converged fit, flagged UNRELIABLE; 0: no limit")
    r.set_defaults(func=cmd_run)
    return [r]
