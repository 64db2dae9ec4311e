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


def _geometry_stage(cap, hidden):
    try:
        from .geometry import estimate_geometry
    except ImportError:
        return None
    return estimate_geometry(cap, hidden=hidden)


def _reflectance_stage(cap, geo, brdf):
    try:
        from .estimate.pipeline import estimate_reflectance
    except ImportError:
        return None
    return estimate_reflectance(cap, geo, brdf=brdf)


def _estimate(cap, hidden, brdf):
    """Geometry then reflectance; returns (geometry estimate, reflectance estimate, json dict)."""
    geo = _geometry_stage(cap, hidden)
    if geo is None:
        raise StircasadiError("The geometry stage (stircasadi.geometry) is not available in this build.")
    if not cap.is_full:  # relay-wall / confocal scans: geometry only
        result = geo.to_json_dict()
        result.setdefault("stages", {})["reflectance"] = {
            "status": "skipped: the capture holds paired traces; the joint reflectance NLP needs "
                      "a full STIR (n_illuminated, n_observed, n_bins)", "success": None}
        return geo, None, result
    est = _reflectance_stage(cap, geo, brdf)
    result = est.to_json_dict(geo) if est is not None else geo.to_json_dict()
    return geo, est, result


def _failed(result: dict) -> bool:
    stages = result.get("stages", {})
    items = stages.values() if isinstance(stages, dict) else stages
    return any(isinstance(s, dict) and s.get("success") is False for s in items)


def cmd_estimate(args) -> int:
    from .capture import Capture

    cap = Capture.read(args.capture)
    try:
        _, _, result = _estimate(cap, args.hidden, args.brdf)
    except SolverError as exc:
        print(f"stircasadi estimate: solver failed: {exc}", file=sys.stderr)
        return 2
    Path(args.out).write_text(json.dumps(result, indent=2, default=_json_default))
    print(f"wrote {args.out}")
    return 1 if _failed(result) else 0


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    return str(o)


def cmd_run(args) -> int:
    from .viz import plot_profiles, render_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
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
    cap_path = cap.write(out / "capture.h5")
    geo = est = None
    result = None
    code = 0
    try:
        t1 = time.perf_counter()
        geo = _geometry_stage(cap, None)
        timings["geometry"] = time.perf_counter() - t1
        if geo is not None:
            t2 = time.perf_counter()
            est = _reflectance_stage(cap, geo, "lambertian")
            if est is not None:
                timings["reflectance"] = time.perf_counter() - t2
    except SolverError as exc:
        print(f"solver failed: {exc}", file=sys.stderr)
        code = 2
    truth = cap.truth
    if geo is not None:
        from .geometry import report_table as geometry_table
        print(geometry_table(geo, truth))
    if est is not None:
        from .estimate.pipeline import report_table
        print(report_table(est, truth, timings=timings))
    if geo is None:
        print("(estimators not available in this build: simulation only)")
    if geo is not None:
        result = est.to_json_dict(geo) if est is not None else geo.to_json_dict()
        (out / "estimate.json").write_text(json.dumps(result, indent=2, default=_json_default))
        if _failed(result):
            code = 1
    pics = [render_scene(scene, out / "scene.png",
                         estimate_positions=_aligned_positions(geo, scene),
                         title=f"{scene.name}: truth (blue/orange) and estimate (green)")]
    pics.append(plot_profiles(cap.stir, cap.grid, out / "profiles.png",
                              title=f"{scene.name}: simulated STIR"))
    timings["total"] = time.perf_counter() - t0
    print("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()))
    report = {"problem": getattr(mod, "NAME", args.problem), "version": __version__,
              "simulation": {k: v for k, v in m.items() if not k.startswith("_")},
              "timings_s": timings, "capture": str(cap_path), "pictures": [str(p) for p in pics],
              "estimate": result}
    (out / "report.json").write_text(json.dumps(report, indent=2, default=_json_default))
    print(f"wrote {out / 'report.json'}, {', '.join(str(p) for p in pics)}")
    return code


def _aligned_positions(geo, scene):
    """Estimated positions in the scene's frame, for the picture: as they are when the estimate
    is in the capture's frame, else mapped about the source onto the visible truth by the
    orthogonal Procrustes solution (a rotation, or a reflection: distances alone cannot tell a
    scene from its mirror image)."""
    if geo is None:
        return None
    P = np.asarray(geo.positions, float)
    if getattr(geo, "frame", None) == "capture":
        return P
    vis = np.asarray(geo.visible, bool)
    ids = np.asarray(geo.ids, int)[vis]
    if vis.sum() < 2 or ids.max() >= scene.n_patches:
        return None
    from .geometry.report import procrustes_matrix

    Q = procrustes_matrix(P[vis] - geo.source_xyz, scene.positions[ids] - scene.source)
    return (P - geo.source_xyz) @ Q + scene.source


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
    e.add_argument("--brdf", choices=["lambertian", "phong"], default="lambertian")
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
