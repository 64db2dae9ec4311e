"""Coverage study of the hidden-surface fit on seeded random twins no one tuned it on.

    python benchmarks/surface_coverage.py [N_SCENES] [FIRST_SEED] [--nodes=12] [--levels=2]
                                          [--prior=none] [--noise=REL] [--FIELD=VALUE ...]
    python benchmarks/surface_coverage.py --rescore=benchmarks/results/surface_coverage_0_23.json

Each scene is ``stircasadi.testing.random_surface_twin(seed)`` (a square, disk, L-shaped letter,
spherical cap or two bars at two depths; depth, tilt, size, albedo, confocal or paired relay and
noise level all drawn from the seed; ``--noise`` sets one relative level for every scene instead, the
rest still drawn: systematic errors of the model hide under the drawn noise and not under a low
one; any other ``--FIELD=VALUE`` sets that field of ``SurfaceSettings``, e.g. ``--edge_extent=1``),
rendered by ``transport.simulate``. The fit sees only the
capture and the wall's known albedo (absolute gain), by the default route a user runs: the
relay from the capture, the volumetric initialiser (LCT confocal, filtered backprojection
otherwise), ``fit_surface`` with its default extent (the initialiser's support) and levels.
``stircasadi.testing.score_surface`` then scores it on the nodes whose whole cell lies on the
truth's support (no depth step inside).

Verdict per scene: FLAGGED when the fit reports ``success`` false (a flagged failure is a good
result); SILENT-WRONG when it reports success but more than a tenth of its mask lies off the
support, or its std maps do not cover the errors of its claims, the depths and albedos of every
full node, those it marks as ``edge`` included (more of them beyond 2 std than calibrated std
give with probability 1 %, binomially, or more than 2 % of them beyond 4 std: tested on all of
them and on the inner and the edge nodes apart; or fewer than half of the full nodes in its
mask); OK otherwise. (Until the edge nodes' std were widened for the edge's model error,
``mask.edge_std``, the claims were the full nodes not marked as edge: at 12 x 12 nodes about 5 %
of them, and only a scene with none of them was judged by its mask's placement. ``--rescore``
judges a study written then by today's rule, from its rows' inner and edge counts.) The pooled
coverage of the OK scenes' claims is the study's measure of calibration; the inner and the edge
nodes' coverage are printed apart. Prints one row per scene and a summary, and writes
``benchmarks/results/surface_coverage_<first>_<last>[_prior<PRIOR>].json`` after every scene.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results"


#: the false-alarm probability of the per-scene coverage test
P_TEST = 0.01


def verdict(success: bool, sc: dict) -> str:
    """FLAGGED, SILENT-WRONG or OK (the module docstring). The coverage test is binomial
    (``stircasadi.testing.coverage_interval``, one-sided): with n claims (a few to a few dozen per
    scene) a scene fails when fewer lie within 2 std than calibrated std give with probability
    ``P_TEST``, or a claim lies beyond 4 std."""
    from stircasadi.testing import coverage_interval, nominal_coverage

    if not success:
        return "FLAGGED"
    if sc["mask_off_support"] > 0.1 * max(sc["mask_nodes"], 1):     # the mask claims a surface where none is
        return "SILENT-WRONG"
    n = claims(sc)[0]
    if n == 0:     # no full node: judged by the mask's placement alone
        return "OK"

    def fails(n, beyond2, beyond4):
        lo, _ = coverage_interval(n, nominal_coverage(2.0), alpha=P_TEST, side="under")
        return n > 0 and (n - beyond2 < lo or beyond4 > 0.02 * n + 0.5)

    # every full node's numbers together, and the inner and the edge nodes' apart (generous edge
    # std must not hide the inner nodes' misses in the pool, nor the reverse)
    if any(fails(*c) for c in claims(sc, parts=True)) or sc["full_in_mask"] < 0.5:
        return "SILENT-WRONG"
    return "OK"


def claims(sc: dict, parts: bool = False):
    """(numbers, beyond 2 std, beyond 4 std) over the depths and albedos of every full node: the
    inner nodes' counts (``n_numbers``, ``beyond2``, ``beyond4``) plus the edge nodes' (their 2
    numbers per node, ``edge_coverage2``, ``edge_beyond4``), so rows written before the edge
    nodes became claims are judged by the same rule. ``parts``: the three triples (pooled,
    inner, edge)."""
    n_edge = 2 * (sc["n_full"] - sc["n_inner"])
    b2_edge = int(round((1.0 - sc["edge_coverage2"]) * n_edge)) if n_edge else 0
    inner = (sc["n_numbers"], sc["beyond2"], sc["beyond4"])
    edge = (n_edge, b2_edge, sc.get("edge_beyond4") or 0)
    pooled = tuple(a + b for a, b in zip(inner, edge))
    return (pooled, inner, edge) if parts else pooled


def run_one(seed: int, nodes: int, levels: int, prior, noise=None, **settings) -> dict:
    """Render seed's twin, fit it by the default route and score it (``noise``: the twin's
    relative noise instead of its drawn one; ``settings``: more fields of ``SurfaceSettings``;
    both for twin experiments)."""
    from stircasadi.nlos import VolumeSettings, backprojection, from_capture, lct
    from stircasadi.nlos.surface import SurfaceSettings, fit_surface
    from stircasadi.testing.surfaces import WALL_RHO, random_surface_twin, score_surface

    t0 = time.perf_counter()
    cap, truth, desc = random_surface_twin(seed, noise=noise)
    t1 = time.perf_counter()
    rl = from_capture(cap)
    rl.gain[:] = (WALL_RHO / np.pi) ** 2
    vol = (lct if rl.confocal else backprojection)(rl, VolumeSettings(gate_m=0.2, n_lateral=16))
    res = fit_surface(rl, vol.maps(), SurfaceSettings(n_nodes=nodes, levels=levels, known_gain=True,
                                                      prior=prior, **settings), gate=0.2)
    sc = score_surface(res, truth)
    pruned = res.levels[-1].get("pruned") or {}
    steps = res.levels[-1].get("steps") or {}
    return {"seed": seed, "scene": desc, "kind": truth["kind"], "relay": truth["relay"],
            "noise": truth["noise"], "render_s": t1 - t0, "fit_s": time.perf_counter() - t1,
            "success": bool(res.success), "chi2_dof": float(res.chi2_dof), "dof": int(res.dof),
            "reasons": list(res.reasons),
            "cut_cells": len((res.extras.get("cell_offsets") or {}).get("nodes", [])),
            "pruned": pruned.get("nodes", 0) if pruned.get("kept") else 0,
            # step 4b stopped once caught up with the first solve (not settled), and what step 4c's
            # test was taken against (``solve`` or ``estimate``)
            "pruned_settled": pruned.get("settled", True),
            "cut_reference": (res.levels[-1].get("cut_cells") or {}).get("reference"),
            # step 4c's extents (``edge_extent``): kept or not, None when not tried; and the
            # numbers of their test (the quadratic model's ratio, the probe's, the final one and
            # the threshold), so that a change of the probe's rule can be judged on a study's rows
            "cut_extent": ((res.levels[-1].get("cut_cells") or {}).get("extent") or {}).get("kept"),
            "cut_extent_test": {k: v for k, v in ((res.levels[-1].get("cut_cells") or {}).get("extent") or {}).items()
                                if k in ("lr_estimate", "threshold", "probed", "lr_probe", "lr", "iterations")} or None,
            "split": steps.get("parts", 0) if steps.get("kept") else 0,
            "subsamples": int(res.levels[-1]["subsamples"]),
            "iterations": [s["iterations"] for lv in res.levels for s in lv["solves"]],
            "verdict": verdict(bool(res.success), sc), **sc}


def _value(text: str):
    """A ``--FIELD=VALUE`` option's value: a number, true/false, else the text."""
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text


def main(argv=None) -> int:
    args = [a for a in (argv if argv is not None else sys.argv[1:])]
    opts = {a.split("=", 1)[0][2:]: a.split("=", 1)[1] for a in args if a.startswith("--") and "=" in a}
    pos = [a for a in args if not a.startswith("--")]
    n = int(pos[0]) if pos else 20
    first = int(pos[1]) if len(pos) > 1 else 0
    nodes, levels = int(opts.get("nodes", 12)), int(opts.get("levels", 2))
    prior = opts.get("prior", "none")
    noise = float(opts["noise"]) if "noise" in opts else None
    known = {"nodes", "levels", "prior", "noise", "rescore"}
    settings = {k: _value(v) for k, v in opts.items() if k not in known}
    try:
        prior = float(prior)
    except ValueError:
        pass
    if "rescore" in opts:
        return rescore(Path(opts["rescore"]))
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / (f"surface_coverage_{first}_{first + n - 1}" + (f"_noise{noise:g}" if noise else "")
                     + ("" if prior == "none" else f"_prior{prior}")
                     + "".join(f"_{k}{v}" for k, v in sorted(settings.items())) + ".json")
    rows = []
    print(f"{'seed':>4} {'kind':<7} {'relay':<8} {'noise':>7} {'full':>4} {'depth MAE mm':>12} {'normal deg':>10} "
          f"{'albedo MAE':>10} {'inner':>5} {'cov2':>5} {'>4sd':>4} {'edge cov2':>9} {'in mask':>7} {'chi2/dof':>8} "
          f"{'q':>2} {'s':>5}  verdict")
    for seed in range(first, first + n):
        try:
            r = run_one(seed, nodes, levels, prior, noise=noise, **settings)
        except Exception as exc:     # recorded, never fatal: the study goes on
            r = {"seed": seed, "verdict": "CRASHED", "error": f"{type(exc).__name__}: {exc}"}
        rows.append(r)
        if r["verdict"] == "CRASHED":
            print(f"{seed:>4} CRASHED {r['error'][:120]}")
        else:
            f = (lambda v, k=1.0, d=2: "-" if v is None else f"{v * k:.{d}f}")
            print(f"{seed:>4} {r['kind']:<7} {r['relay']:<8} {r['noise']:>7.4f} {r['n_full']:>4} "
                  f"{f(r['depth_mae'], 1e3):>12} {f(r['normal_deg_median'], 1, 1):>10} {f(r['albedo_mae'], 1, 3):>10} "
                  f"{r['n_inner']:>5} {f(r['coverage2']):>5} {r['beyond4']:>4} {f(r['edge_coverage2']):>9} "
                  f"{f(r['full_in_mask']):>7} {r['chi2_dof']:>8.3f} {r['subsamples']:>2} "
                  f"{r['fit_s']:>5.0f}  {r['verdict']}", flush=True)
        out.write_text(json.dumps({"settings": {"nodes": nodes, "levels": levels, "prior": prior, "noise": noise,
                                                **settings},
                                   "rows": rows}, indent=1, default=float))
    return summary(rows, out)


def summary(rows: list, out: Path) -> int:
    """Print the verdicts and the pooled coverage; 1 when a scene is SILENT-WRONG or crashed."""
    counts = {v: sum(r["verdict"] == v for r in rows) for v in ("OK", "FLAGGED", "SILENT-WRONG", "CRASHED")}
    print("verdicts", counts)

    ok = [r for r in rows if r["verdict"] == "OK"]
    scored = [r for r in rows if r["verdict"] != "CRASHED"]

    def within(sel, part=0):       # part of ``claims(parts=True)``: 0 pooled, 1 inner, 2 edge
        c = [claims(r, parts=True)[part] for r in sel]
        n = sum(k[0] for k in c)
        return ((n - sum(k[1] for k in c)) / n if n else float("nan")), n, sum(k[2] for k in c)

    (c_ok, n_ok, b4_ok), (c_all, n_all, _) = within(ok), within(scored)
    (c_in, n_in, _), (c_edge, n_edge, _) = within(ok, 1), within(ok, 2)
    print(f"claims (every full node's depth and albedo) within 2 std: OK scenes {c_ok:.3f} of {n_ok} "
          f"({b4_ok} beyond 4 std), every scene {c_all:.3f} of {n_all}; of the OK scenes' claims, inner nodes "
          f"{c_in:.3f} of {n_in}, edge nodes {c_edge:.3f} of {n_edge}")
    print("written", out)
    return 1 if counts["SILENT-WRONG"] or counts["CRASHED"] else 0


def rescore(path: Path) -> int:
    """Recompute the verdicts of a written study (``--rescore=FILE``) with this script's rule."""
    doc = json.loads(Path(path).read_text())
    for r in doc["rows"]:
        if r["verdict"] != "CRASHED":
            r["verdict"] = verdict(r["success"], r)
    Path(path).write_text(json.dumps(doc, indent=1, default=float))
    return summary(doc["rows"], Path(path))


if __name__ == "__main__":
    sys.exit(main())
