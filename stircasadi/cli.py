"""The ``stircasadi`` command (DESIGN.md section 5).

    stircasadi run [PROBLEM] [--out DIR]          simulate, estimate, table vs truth, report
    stircasadi simulate PROBLEM --out capture.h5 [--noise none] [--seed N]
    stircasadi estimate CAPTURE --out estimate.json [--hidden N] [--brdf lambertian|phong]
    stircasadi import FILE --format FORMAT --out capture.h5
    stircasadi acquire --port PORT ... --out capture.h5
    stircasadi problems                           list the problem scripts
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from . import __version__
from .errors import SolverError, StircasadiError


def _simulate_problem(name: str | None, noise: bool = True, seed: int = 0, bounces=None):
    from .problem import load_problem
    from .transport import simulate

    mod = load_problem(name)
    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    tr = simulate(scene, grid, sensor=sensor, bounces=bounces)
    cap = sensor.capture(tr, seed=seed, noise=noise)
    priors = getattr(mod, "PRIORS", None)
    if priors:  # the experimenter's declared knowledge travels with the capture (priors/ group)
        cap.extras["priors"] = {"__attrs__": {k: (json.dumps({str(i): a for i, a in v.items()})
                                                   if isinstance(v, dict) else v)
                                              for k, v in priors.items()}}
    return mod, scene, tr, cap


def cmd_simulate(args) -> int:
    _, scene, tr, cap = _simulate_problem(args.problem, noise=args.noise != "none", seed=args.seed,
                                          bounces=args.bounces)
    out = cap.write(args.out)
    m = tr.metadata
    print(f"{scene.describe()}\nwrote {out}: STIR {cap.stir.shape}, method={m['method']}, "
          f"bounces={m['bounces']}, irf={m['irf']}, noise={cap.noise.get('model')}, "
          f"{m['wall_time_s']:.3f} s")
    return 0


EXIT_UNRELIABLE = 3


def _areas_arg(v):
    if v is None:
        return None
    p = Path(v)
    try:
        if p.suffix.lower() == ".json" or p.exists():
            d = json.loads(p.read_text())
        else:
            d = json.loads(v)
        return {int(k): float(a) for k, a in d.items()}
    except (OSError, ValueError, AttributeError, TypeError) as exc:
        raise StircasadiError(f"--areas must be a JSON object {{patch id: area in m^2}} or a .json file "
                              f"holding one; got {v!r} ({exc}).") from exc


def cmd_estimate(args) -> int:
    from .capture import Capture
    from .io import atomic_write_text, check_output
    from .pipeline import estimate_capture
    from .report import dumps, table

    out = check_output(args.out, inputs=[args.capture], what="estimate", suffixes=(".json",))
    cap = Capture.read(args.capture)
    try:
        res = estimate_capture(cap, hidden=args.hidden, brdf=args.brdf, areas=_areas_arg(args.areas),
                               flatland=True if args.flatland else None)
    except SolverError as exc:
        print(f"stircasadi estimate: solver failed: {exc}", file=sys.stderr)
        return 2
    d = res.to_json_dict()
    atomic_write_text(out, dumps(d))
    if d.get("patches") and d.get("version") == 2 and "reasons" in d:
        print(table(d))
    print(f"verdict: {d.get('verdict')}" + ("" if d.get("success") else
                                           " — " + "; ".join(d.get("reasons", []))))
    print(f"wrote {out}")
    return 0 if d.get("success") else EXIT_UNRELIABLE


def _known_geometry(mod, scene, cap) -> str | None:
    """A problem that exercises one stage (``ESTIMATE = {"stage": "reflectance"}``: a reflectance
    twin with known geometry) gives its visible points, normals and areas to the estimator, as a
    calibrated scanner would; says so."""
    opts = getattr(mod, "ESTIMATE", {}) or {}
    if opts.get("stage") != "reflectance":
        return None
    obs = cap.obs_ids()
    cap.observed_xyz = scene.positions[obs]
    cap.extras["observed_normals"] = scene.normals[obs]
    pri = dict(cap.extras.get("priors", {"__attrs__": {}}).get("__attrs__", {}))
    pri["areas"] = json.dumps({str(int(i)): float(scene.areas[i]) for i in obs})
    cap.extras["priors"] = {"__attrs__": pri}
    return "stage: reflectance only (the problem gives the visible geometry and areas)"


def cmd_run(args) -> int:
    from .io import atomic_write_text, check_output
    from .pipeline import estimate_capture
    from .report import dumps, table
    from .viz import plot_profiles, render_scene

    out = check_output(args.out, what="output", folder=True)
    timings = {}
    t0 = time.perf_counter()
    mod, scene, tr, cap = _simulate_problem(args.problem, seed=args.seed)
    timings["simulate"] = time.perf_counter() - t0
    m = tr.metadata
    print(f"stircasadi {__version__} — problem '{getattr(mod, 'NAME', args.problem)}'")
    print(scene.describe())
    print(f"simulated STIR {cap.stir.shape} on {tr.grid}: method={m['method']}, bounces={m['bounces']}, "
          f"irf={m['irf']}, occlusion={m['occlusion']}, noise={cap.noise.get('model')}; "
          f"omitted energy {m.get('omitted_energy_rel', 0.0):.2e}")
    stage = _known_geometry(mod, scene, cap)
    if stage:
        print(stage)
    out.mkdir(parents=True, exist_ok=True)
    truth = cap.truth
    cap_path = cap.write(out / "capture.h5")
    blind = cap
    blind.truth = None  # the estimator never sees the truth
    opts = dict(getattr(mod, "ESTIMATE", {}) or {})
    t1 = time.perf_counter()
    try:
        res = estimate_capture(blind, brdf=opts.get("brdf", "lambertian"), hidden=opts.get("hidden"))
    except SolverError as exc:
        print(f"solver failed: {exc}", file=sys.stderr)
        return 2
    timings["estimate"] = time.perf_counter() - t1
    cap.truth = truth
    d = res.to_json_dict()
    print(table(d, truth))
    for c in d.get("checks", []):
        if not c["passed"]:
            print(f"check failed: {c['name']}: {c['message']}")
    print(f"verdict: {d['verdict']}" + ("" if d["success"] else " — " + "; ".join(d["reasons"])))
    atomic_write_text(out / "estimate.json", dumps(d))
    pics = []
    try:
        pics.append(render_scene(scene, out / "scene.png", estimate_positions=_aligned_positions(d, truth),
                                 title=f"{scene.name}: truth (blue/orange) and estimate (green)"))
    except Exception as exc:  # a picture never costs a result
        print(f"scene picture skipped: {type(exc).__name__}: {exc}", file=sys.stderr)
    pics.append(plot_profiles(cap.stir, cap.grid, out / "profiles.png", title=f"{scene.name}: simulated STIR"))
    timings["total"] = time.perf_counter() - t0
    print("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()))
    report = {"problem": getattr(mod, "NAME", args.problem), "version": __version__,
              "simulation": {k: v for k, v in m.items() if not k.startswith("_")},
              "timings_s": timings, "capture": str(cap_path), "pictures": [str(p) for p in pics]}
    atomic_write_text(out / "report.json", dumps(report))
    print(f"wrote {out / 'capture.h5'}, {out / 'estimate.json'}, {out / 'report.json'}, "
          f"{', '.join(str(p) for p in pics)}")
    return 0 if d["success"] else EXIT_UNRELIABLE


def _aligned_positions(d, truth):
    """Estimated positions in the truth's frame (for the picture): ``report.alignment``."""
    from .report import alignment, vec

    Q, s, st = alignment(d, truth)
    P = np.array([vec(p.get("position")) for p in d["patches"]])
    return (P - s) @ Q + st


def cmd_problems(args) -> int:
    from .problem import DEFAULT_PROBLEM, describe, list_problems, load_problem

    names = list_problems()
    width = max(len(p) for p in names)
    for p in names:
        print(f"{p:<{width}}  {describe(load_problem(p))}" + ("  [default]" if p == DEFAULT_PROBLEM else ""))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="stircasadi", description="Inverse transient light transport.")
    p.add_argument("--version", action="version", version=f"stircasadi {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="simulate a problem, estimate it, print a table against the truth")
    r.add_argument("problem", nargs="?", default=None, help="problem name or path (default: hidden_corner)")
    r.add_argument("--out", default="runs/latest", help="folder for capture, estimate, report, pictures")
    r.add_argument("--seed", type=int, default=0)
    r.set_defaults(func=cmd_run)

    s = sub.add_parser("simulate", help="write a problem's STIR through its sensor model")
    s.add_argument("problem")
    s.add_argument("--out", required=True)
    s.add_argument("--noise", choices=["sensor", "none"], default="sensor",
                   help="'none' writes the ideal, noise-free STIR")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--bounces", default=None, type=lambda v: v if v == "all" else int(v),
                   help="bounce order (default: what the scene needs) or 'all'")
    s.set_defaults(func=cmd_simulate)

    e = sub.add_parser("estimate", help="estimate geometry and reflectance from a capture")
    e.add_argument("capture")
    e.add_argument("--out", required=True)
    e.add_argument("--hidden", type=int, default=None, help="number of hidden patches (default: detect)")
    e.add_argument("--brdf", choices=["lambertian", "phong"], default="lambertian",
                   help="reflectance model of the visible patches (default: %(default)s)")
    e.add_argument("--areas", default=None,
                   help="declared patch areas: a JSON object {id: m^2} or a .json file (default: "
                        "estimated where the data identify them)")
    e.add_argument("--flatland", action="store_true",
                   help="declare that every patch lies in the plane of the source and the visible "
                        "patches (as in the paper's Fig. 12)")
    e.set_defaults(func=cmd_estimate)

    pr = sub.add_parser("problems", help="list the problem scripts")
    pr.set_defaults(func=cmd_problems)

    try:
        from .acquisition.cli import add_parsers
    except ImportError:
        add_parsers = None
    if add_parsers is not None:
        add_parsers(sub)
    try:
        from .apps.cli import add_parsers as add_app_parsers
    except ImportError:
        add_app_parsers = None
    if add_app_parsers is not None:
        add_app_parsers(sub)
    try:
        from .studies.cli import add_parsers as add_study_parsers
    except ImportError:
        add_study_parsers = None
    if add_study_parsers is not None:
        add_study_parsers(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except StircasadiError as exc:
        print(f"stircasadi {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
