"""Forward-model benchmark: time and peak memory of a full STIR against the number of patches.

For M in {10, 50, 147, 500} patches on three planes and 2048 bins, each method:

* ``frequency-all``  the all-bounce resolvent (Gaussian 210 ps impulse response);
* ``bounces-K2`` / ``bounces-K3``  exact path sums to 2 / 3 bounces;
* ``statespace-link``  the paper's explicit shift-register state space, one state per bin of
  delay per link L_ij (integer delays) -- the baseline;
* ``statespace-node``  the same with one register per patch (Lambertian nodes).

Each case runs in its own process (peak RSS from getrusage) with a time limit. The state-space
baselines are too slow for all illuminated patches at large M: their cost is linear in the
number of pulses (one column of the state matrix each), so they are run for a subset of the
pulses and scaled up, and the table says so.

    python benchmarks/forward.py            # full table (about 15 minutes on 2 cores)
    python benchmarks/forward.py --quick    # M in {10, 50}
Writes benchmarks/results/forward.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
N_BINS = 2048


def build_scene(M: int):
    """M Lambertian patches split over three planes facing the origin (like Fig. 11)."""
    import numpy as np

    sys.path.insert(0, str(HERE.parent))
    from stircasadi.problems._common import plane_patches, unit
    from stircasadi.scene import Scene

    per = [M - 2 * (M // 3), M // 3, M // 3]
    specs = [((0.0, 0.0, 1.6), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0)),
             ((-0.75, 0.0, 1.1), tuple(unit((0.8, 0.0, -0.6))), (0.0, 1.0, 0.0)),
             ((0.75, 0.05, 1.1), tuple(unit((-0.8, 0.1, -0.6))), (0.0, 1.0, 0.0))]
    rng = np.random.default_rng(0)
    patches = []
    for n, (c, nrm, u) in zip(per, specs):
        nu = int(np.ceil(np.sqrt(n)))
        grid = plane_patches(c, nrm, u, nu, nu, 0.9 / nu, (0.6 / nu) ** 2,
                             albedos=rng.uniform(0.3, 0.9, nu * nu))
        patches += grid[:n]
    return Scene(patches, name=f"planes{M}")


def run_case(M: int, method: str, n_pulses: int | None) -> dict:
    import numpy as np

    from stircasadi.irf import GaussianIRF
    from stircasadi.sensor import Sensor
    from stircasadi.timegrid import TimeGrid
    from stircasadi.transport import TransportSystem, simulate
    from stircasadi.transport.statespace import build_state_space, simulate_state_space

    scene = build_scene(M)
    grid = TimeGrid(0.0, 0.01, N_BINS)
    sensor = Sensor(GaussianIRF.from_ps(210.0))
    t0 = time.perf_counter()
    info: dict = {}
    if method == "frequency-all":
        tr = simulate(scene, grid, sensor, method="frequency", bounces="all")
        info = {"n_frequencies": tr.metadata["n_frequencies"], "fft_length": tr.metadata["fft_length"],
                "alias_energy_bound_rel": tr.metadata["alias_energy_bound_rel"]}
        checksum = float(tr.stir.sum())
    elif method.startswith("bounces"):
        K = int(method[-1])
        tr = simulate(scene, grid, sensor, method="bounces", bounces=K)
        checksum = float(tr.stir.sum())
    else:
        link = method.endswith("link")
        sysm = TransportSystem.build(scene, delay_mode="integer", bin_width=grid.bin_width,
                                     link_level=link)
        if n_pulses is not None and n_pulses < sysm.n_ill:
            keep = np.isin(sysm.S[1], np.arange(n_pulses))
            sysm.S = tuple(x[keep] for x in sysm.S)
            sysm.ill_ids = sysm.ill_ids[:n_pulses]
        t_build = time.perf_counter()
        ss = build_state_space(sysm)
        info = {"n_states": ss.n_states, "nnz_A": int(ss.A.nnz),
                "build_s": time.perf_counter() - t_build}
        stir = simulate_state_space(ss, sysm, grid, sensor.irf)
        checksum = float(stir.sum())
    wall = time.perf_counter() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"M": M, "method": method, "wall_s": wall, "peak_rss_mb": peak_mb,
            "n_pulses_run": n_pulses, "checksum": checksum, **info}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--timeout", type=float, default=900.0)
    ap.add_argument("--case", nargs=3, metavar=("M", "METHOD", "PULSES"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.case:
        M, method, pulses = int(args.case[0]), args.case[1], args.case[2]
        print(json.dumps(run_case(M, method, None if pulses == "all" else int(pulses))))
        return
    Ms = [10, 50] if args.quick else [10, 50, 147, 500]
    plan = []
    for M in Ms:
        plan.append((M, "frequency-all", "all"))
        plan.append((M, "bounces-K2", "all"))
        if M <= 147:
            plan.append((M, "bounces-K3", "all"))
        ss_pulses = {10: "all", 50: "all", 147: "4", 500: "1"}[M]
        if M <= 147:
            plan.append((M, "statespace-link", {10: "all", 50: "5", 147: "1"}[M]))
        plan.append((M, "statespace-node", ss_pulses))
    rows = []
    for M, method, pulses in plan:
        cmd = [sys.executable, __file__, "--case", str(M), method, pulses]
        t0 = time.perf_counter()
        try:
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=args.timeout, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
        except subprocess.TimeoutExpired:
            row = {"M": M, "method": method, "wall_s": None, "timeout_s": args.timeout,
                   "n_pulses_run": None if pulses == "all" else int(pulses)}
        except subprocess.CalledProcessError as exc:
            row = {"M": M, "method": method, "error": exc.stderr.strip().splitlines()[-1:]}
        n_run = row.get("n_pulses_run")
        if row.get("wall_s") is not None and n_run:
            row["wall_s_full_estimate"] = row["wall_s"] * M / n_run  # linear in the number of pulses
        elif row.get("wall_s") is not None:
            row["wall_s_full_estimate"] = row["wall_s"]
        rows.append(row)
        full = row.get("wall_s_full_estimate")
        print(f"M={M:4d} {method:16s} pulses={pulses:>4s}  wall={row.get('wall_s') or float('nan'):9.3f} s  "
              f"full-STIR={full if full is not None else float('nan'):10.3f} s  "
              f"peak={row.get('peak_rss_mb', float('nan')):8.1f} MB  {row.get('n_states', '')}",
              flush=True)
        del t0
    # speed-up of the all-bounce solve against the paper's state space
    for M in Ms:
        f = next((r for r in rows if r["M"] == M and r["method"] == "frequency-all"), None)
        s = next((r for r in rows if r["M"] == M and r["method"] == "statespace-link"), None)
        if f and s and f.get("wall_s") and s.get("wall_s_full_estimate"):
            print(f"M={M}: all-bounce frequency is {s['wall_s_full_estimate'] / f['wall_s']:.0f}x faster "
                  "than the paper's link-level state space")
    res = {"machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                       "python": platform.python_version()},
           "n_bins": N_BINS, "rows": rows}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "forward.json").write_text(json.dumps(res, indent=2))
    print(f"wrote {HERE / 'results' / 'forward.json'}")


if __name__ == "__main__":
    main()
