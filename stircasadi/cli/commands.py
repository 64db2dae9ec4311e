"""``stircasadi simulate``, ``stircasadi estimate`` and ``stircasadi problems``.

Each command checks its inputs (argument types, ``cli.args``) and its output path
(``stircasadi.io.check_output``: not an input, a writable folder that exists) before any work,
writes atomically, and prints what it did. ``simulate_problem`` and ``known_geometry`` are shared
with ``stircasadi run``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

from ..errors import StircasadiError
from ..progress import get_logger
from . import args as A

__all__ = ["add_parsers", "simulate_problem", "known_geometry", "script_inputs", "cmd_simulate",
           "cmd_estimate", "cmd_problems"]

log = get_logger(__name__)
CAPTURE_SUFFIXES = (".h5", ".hdf5", ".hdf")
#: relay-wall reconstructions of ``stircasadi.nlos`` (volumes; a fitted surface)
NLOS_METHODS = ("lct", "fk", "bp", "surface")


def script_inputs(problem: str | None) -> list:
    """The input files of a problem argument (a script path), for the output checks."""
    p = Path(problem) if problem else None
    return [p] if p is not None and p.is_file() else []


def simulate_problem(name_or_mod, noise: bool = True, seed: int = 0, bounces=None):
    """(module, scene, transient, capture) of a problem simulated through its sensor; the
    problem's declared ``PRIORS`` travel with the capture (its ``priors/`` group)."""
    from ..problem import load_problem, problem_name
    from ..transport import simulate

    mod = load_problem(name_or_mod) if not hasattr(name_or_mod, "build_scene") else name_or_mod
    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    log.info(f"simulating '{problem_name(mod)}': {scene.n_patches} patches, {grid.n_bins} bins")
    tr = simulate(scene, grid, sensor=sensor, bounces=bounces)
    cap = sensor.capture(tr, seed=seed, noise=noise)
    priors = getattr(mod, "PRIORS", None)
    if priors:
        cap.extras["priors"] = {"__attrs__": {k: (json.dumps({str(i): a for i, a in v.items()})
                                                   if isinstance(v, dict) else v)
                                              for k, v in priors.items()}}
    return mod, scene, tr, cap


def known_geometry(mod, scene, cap) -> str | None:
    """A problem that exercises one stage (``ESTIMATE = {"stage": "reflectance"}``: a reflectance
    twin with known geometry) gives its visible points, normals and areas to the estimator, as a
    calibrated scanner would; returns the line saying so (None otherwise)."""
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


def describe_simulation(tr, cap) -> str:
    from ..constants import C

    m = tr.metadata
    g = cap.grid
    return (f"simulated STIR {' x '.join(map(str, cap.stir.shape))} (pulses x seen patches x bins of "
            f"{g.bin_width * 1e3:g} mm = {g.bin_width / C * 1e12:.1f} ps): method {m['method']}, "
            f"bounces {m['bounces']}, impulse response {m['irf']}, occlusion {m['occlusion']}, noise "
            f"{cap.noise.get('model')}; energy left out {m.get('omitted_energy_rel', 0.0):.1e}")


def cmd_simulate(args) -> int:
    from ..io import check_output

    out = check_output(args.out, inputs=script_inputs(args.problem), what="capture",
                       suffixes=CAPTURE_SUFFIXES)
    t0 = time.perf_counter()
    _, scene, tr, cap = simulate_problem(args.problem, noise=args.noise != "none", seed=args.seed,
                                         bounces=args.bounces)
    cap.write(out, inputs=script_inputs(args.problem))
    print(scene.describe())
    print(describe_simulation(tr, cap))
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB) in {time.perf_counter() - t0:.2f} s")
    return 0


def cmd_estimate(args) -> int:
    from ..capture import Capture
    from ..io import atomic_write_text, check_output
    from ..pipeline import estimate_capture
    from ..report import dumps, table
    from .main import EXIT_UNRELIABLE
    from .summary import print_summary

    out = check_output(args.out, inputs=[args.capture], what="estimate", suffixes=(".json",))
    maps = None
    if args.method in NLOS_METHODS:
        maps = check_output(args.maps or out.with_name(out.stem + "_nlos"), inputs=[args.capture],
                            what="maps", folder=True)
    elif args.maps is not None:
        raise StircasadiError(f"--maps is for --method {'|'.join(NLOS_METHODS)} (relay-wall volumes and "
                              f"surfaces); got --method {args.method or 'automatic'}.")
    nlos = dict(args.nlos)
    if nlos and args.method not in NLOS_METHODS:
        raise StircasadiError(f"--nlos is for --method {'|'.join(NLOS_METHODS)} (relay-wall volumes and "
                              f"surfaces); got --method {args.method or 'automatic'}.")
    t0 = time.perf_counter()
    cap = Capture.read(args.capture)
    truth, cap.truth = cap.truth, None  # the estimator never sees a truth group
    log.info(f"estimating from {args.capture}: "
             + (f"STIR {' x '.join(map(str, cap.stir.shape))}" if cap.stir is not None
                else f"{len(cap.traces)} paired traces"))
    res = estimate_capture(cap, hidden=args.hidden, brdf=args.brdf, areas=args.areas,
                           flatland=True if args.flatland else None, method=args.method, out_dir=maps,
                           time_limit=args.time_limit, nlos_options=nlos or None)
    d = res.to_json_dict()
    atomic_write_text(out, dumps(d))
    if maps is not None:
        print(f"volumes, maps, mesh and pictures in {maps}")
    print(table(d, truth))
    if truth is not None:
        print("(err/σ: against the capture's truth/ group, which the estimator did not read)")
    print_summary(d)
    print(f"wrote {out} in {time.perf_counter() - t0:.2f} s")
    return 0 if d.get("success") else EXIT_UNRELIABLE


def cmd_problems(args) -> int:
    from ..problem import DEFAULT_PROBLEM, describe, list_problems, load_problem

    names = list_problems()
    width = max(len(p) for p in names)
    for p in names:
        print(f"{p:<{width}}  {describe(load_problem(p))}" + ("  [default]" if p == DEFAULT_PROBLEM else ""))
    print("run one with: stircasadi run NAME   (or a path to your own problem script)")
    return 0


def add_parsers(sub) -> list:
    s = sub.add_parser("simulate", formatter_class=A.Formatter,
                       help="write a problem's simulated capture (its STIR through its sensor)",
                       description="Simulate a problem through its sensor model and write the Capture "
                                   "(HDF5, with the truth in its truth/ group).")
    s.add_argument("problem", type=A.problem, help="problem name (see 'stircasadi problems') or a path "
                                                    "to a problem script")
    s.add_argument("--out", required=True, help="Capture file to write (.h5); never an input")
    s.add_argument("--noise", choices=["sensor", "none"], default="sensor",
                   help="'sensor': the problem's noise model; 'none': the ideal, noise-free STIR")
    s.add_argument("--seed", type=A.seed, default=0, help=f"noise seed, 0 to {A.SEED_MAX}")
    s.add_argument("--bounces", type=A.bounces, default=None,
                   help=f"bounce order 1 to {A.BOUNCES_MAX} or 'all' (default: what the scene needs: "
                        "3 with hidden patches, else 2)")
    s.set_defaults(func=cmd_simulate)

    e = sub.add_parser("estimate", formatter_class=A.Formatter,
                       help="estimate geometry, reflectance and hidden patches from a capture",
                       description="Estimate every patch (positions, normals, albedos, areas, hidden "
                                   "patches) with its standard deviation, check the estimate against "
                                   "the data, and write estimate.json (schema: docs/estimate-json.md). "
                                   "Exit status 0: OK; 3: UNRELIABLE (written, with the reasons).")
    e.add_argument("capture", type=A.capture_file, help="Capture HDF5 file (stircasadi simulate, "
                                                        "import or acquire)")
    e.add_argument("--out", required=True, help="estimate.json to write; never the capture")
    e.add_argument("--hidden", type=A.hidden, default=None,
                   help=f"place exactly this many hidden patches, 0 to {A.HIDDEN_MAX} (default: as "
                        "many as the data ask for)")
    e.add_argument("--brdf", choices=["lambertian", "phong"], default="lambertian",
                   help="reflectance model of the visible patches")
    e.add_argument("--areas", type=A.areas, default=None,
                   help="declared patch areas: a JSON object {id: m^2} or a .json file holding one "
                        "(default: estimated where the data identify them)")
    e.add_argument("--method", choices=["joint", "relay", *NLOS_METHODS], default=None,
                   help="estimator (default: 'joint' for a full STIR with its source and camera legs, "
                        "'relay' for relay-wall scans); relay-wall scans also take 'lct', 'fk', 'bp' "
                        "(volumes) or 'surface' (a fitted hidden surface); a full STIR also takes "
                        "'surface' (the visible patches' joint fit, then the hidden surface behind "
                        "them from their third bounce, as in the paper's Fig. 13)")
    e.add_argument("--maps", type=Path, default=None,
                   help="folder for the volumes, maps, mesh and pictures of --method lct|fk|bp|surface "
                        "(default: OUT_nlos beside the estimate)")
    e.add_argument("--nlos", type=A.nlos_option, action="append", default=[], metavar="KEY=VALUE",
                   help="an option of --method lct|fk|bp|surface on a relay-wall scan, repeatable: a "
                        "field of stircasadi.nlos VolumeSettings or SurfaceSettings, or init / "
                        "wall_step / gain (e.g. --nlos wall_step=4 --nlos bin_factor=4 --nlos "
                        "n_nodes=16 --nlos prior=auto); an unknown key is refused with the known ones")
    e.add_argument("--time-limit", type=A.time_limit, default=A.TIME_LIMIT_DEFAULT, metavar="SECONDS",
                   help="wall-clock limit of the estimate: where it runs out, the stages left are skipped "
                        "and the result is the last converged fit, flagged UNRELIABLE (check time-limit); "
                        "0: no limit")
    e.add_argument("--flatland", action="store_true",
                   help="declare that every patch lies in the plane of the source and the visible "
                        "patches (as in the paper's Fig. 12)")
    e.set_defaults(func=cmd_estimate)

    pr = sub.add_parser("problems", formatter_class=A.Formatter, help="list the problems, one line each")
    pr.set_defaults(func=cmd_problems)
    return [s, e, pr]
