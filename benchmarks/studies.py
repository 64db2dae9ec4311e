"""Study-engine benchmark: the per-cell overhead of the engine and the scaling from 1 to N workers.

1. **Overhead.** ``N`` trivial cells (three_patch simulated, no estimate: a few ms each) run
   (a) as a bare loop of ``run_cell`` -- the work itself --, (b) through ``run_study`` serially
   (hashing, the atomic, fsync'ed cache write of every record), (c) on a LocalCluster of 1 and
   2 workers (scheduling, pickling, transfer). The fixed cost of a run (reading the cache,
   tables, provenance) is the wall of an immediate rerun (every cell cached); the cluster
   start-up is timed apart. Overhead per cell = (wall - start-up - fixed - work / workers) / N.
2. **Scaling.** A real study (``accuracy-vs-time`` at size ``medium``: 240 cells of the two
   small problems, every solver and bin width; or ``--study NAME --size SIZE``) on 1 and on 2
   workers: wall time and speed-up. Each run starts from an empty results folder.

    python benchmarks/studies.py                 # about 4 minutes on 2 cores
    python benchmarks/studies.py --cells 100 --study hard-cases --size smoke
Writes benchmarks/results/studies.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def trivial_study(n: int) -> dict:
    return {"name": "overhead", "repetitions": n, "seed": 0,
            "base": {"problem": "three_patch", "estimate": False}}


def timed_run(spec, out, size=None, workers=0):
    from stircasadi.studies import RunSettings, run_study

    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    res = run_study(spec, out, size=size, settings=RunSettings(workers=workers, figures=False))
    wall = time.perf_counter() - t
    return wall, res


def cluster_startup(workers: int) -> float:
    from stircasadi.studies import local_cluster

    t = time.perf_counter()
    with local_cluster(workers) as client:
        client.submit(sum, [1, 2]).result()
        up = time.perf_counter() - t
    return up


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", type=int, default=200, help="trivial cells of the overhead runs")
    ap.add_argument("--study", default="accuracy-vs-time")
    ap.add_argument("--size", default="medium")
    ap.add_argument("--workers", type=int, default=2, help="the largest cluster of the scaling run")
    args = ap.parse_args(argv)

    sys.path.insert(0, str(HERE.parent))
    from stircasadi import __version__
    from stircasadi.studies import load_study, run_cell

    tmp = Path(tempfile.mkdtemp(prefix="stircasadi-bench-"))
    rows = []
    try:
        # ---------------------------------------------------------------- 1. overhead
        spec = trivial_study(args.cells)
        cells = load_study(spec).cells()
        run_cell(cells[0])                                   # imports, first-call costs
        t = time.perf_counter()
        for c in cells:
            run_cell(c)
        bare = time.perf_counter() - t
        rows.append({"run": "bare run_cell loop", "cells": len(cells), "wall_s": bare,
                     "per_cell_ms": 1e3 * bare / len(cells), "overhead_ms": 0.0})
        for workers in [0] + list(range(1, args.workers + 1)):
            up = cluster_startup(workers) if workers else 0.0
            wall, res = timed_run(spec, tmp / f"o{workers}", workers=workers)
            t = time.perf_counter()
            from stircasadi.studies import RunSettings, run_study

            run_study(spec, tmp / f"o{workers}", settings=RunSettings(workers=0, figures=False))
            fixed = time.perf_counter() - t
            work = float(res.cells["wall_s"].sum())
            label = "run_study serial" if workers == 0 else f"run_study {workers} worker(s)"
            rows.append({"run": label, "cells": len(res.cells), "wall_s": wall, "startup_s": up,
                         "fixed_s": fixed, "work_s": work, "per_cell_ms": 1e3 * wall / len(res.cells),
                         "overhead_ms": 1e3 * (wall - up - fixed - work / max(workers, 1)) / len(res.cells)})
        # ---------------------------------------------------------------- 2. scaling
        scal = []
        for workers in range(1, args.workers + 1):
            wall, res = timed_run(args.study, tmp / f"s{workers}", size=args.size, workers=workers)
            scal.append({"study": f"{args.study}@{args.size}", "workers": workers, "cells": len(res.cells),
                         "wall_s": wall, "work_s": float(res.cells["wall_s"].sum()),
                         "ok": int((res.cells["status"] == "ok").sum())})
        for s in scal:
            s["speedup"] = scal[0]["wall_s"] / s["wall_s"]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"stircasadi {__version__}, {platform.node()}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} at the end")
    print(f"\nper-cell overhead ({args.cells} trivial cells: three_patch simulated, no estimate)")
    print(f"{'run':<26} {'cells':>5} {'wall s':>8} {'start s':>8} {'fixed s':>8} {'work s':>8} "
          f"{'ms/cell':>8} {'overhead ms/cell':>17}")
    for r in rows:
        print(f"{r['run']:<26} {r['cells']:>5} {r['wall_s']:8.2f} {r.get('startup_s', 0):8.2f} "
              f"{r.get('fixed_s', 0):8.2f} {r.get('work_s', r['wall_s']):8.2f} {r['per_cell_ms']:8.1f} "
              f"{r['overhead_ms']:17.1f}")
    print(f"\nscaling: {args.study}@{args.size}")
    print(f"{'workers':>7} {'cells':>5} {'ok':>4} {'wall s':>8} {'work s':>8} {'speed-up':>8}")
    for s in scal:
        print(f"{s['workers']:>7} {s['cells']:>5} {s['ok']:>4} {s['wall_s']:8.1f} {s['work_s']:8.1f} {s['speedup']:8.2f}")
    out = HERE / "results" / "studies.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps({"version": __version__, "node": platform.node(), "cpus": os.cpu_count(),
                               "loadavg": os.getloadavg(),
                               "overhead": rows, "scaling": scal}, indent=2))
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
