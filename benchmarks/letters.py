"""The surface fit on a Stanford letter scan: does the letter show in its albedo map?

    python benchmarks/letters.py [--file data_diffuse_s.mat] [--t-max 1.4] [--diffuse 1]
                                 [--wall-step 2] [--nodes 16] [--levels 2] [--prior auto]
                                 [--max-iter 12] [--gate 0.6] [--init-fraction 0.25]

The scan is read from ``$STIRCASADI_DATA/otoole2018_confocal``, binned to 16 ps, gated at
``--gate`` metres of path and the LCT volume cut at ``--t-max`` (the surface fit sees the whole
record). Wall points are summed in ``--wall-step`` x ``--wall-step`` blocks; a letter needs at
least 32 x 32 traces (notebook 05, "How many wall points does a letter need?"). The fit is
initialised by LCT and runs coarse to fine. It prints one row with the wall time, the process's
maximum resident memory, chi2/dof, the mask's size, ``success`` and the reasons. It writes
``benchmarks/results/letters_<file>_<nodes>.json``, the maps (``.npz``) and a picture ``.png``
beside it: the LCT initialiser's albedo, the surface's albedo over the grid and inside the mask,
and its depth inside the mask, all seen from the wall.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stircasadi.acquisition.importers import read_stanford_lct  # noqa: E402
from stircasadi.datasets import data_dir  # noqa: E402
from stircasadi.nlos import estimate_capture  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--file", default="data_diffuse_s.mat")
    ap.add_argument("--t-max", type=float, default=1.4, help="metres of path kept")
    ap.add_argument("--diffuse", type=int, default=1, help="1: Lambertian falloff in LCT, 0: retroreflective")
    ap.add_argument("--wall-step", type=int, default=2)
    ap.add_argument("--nodes", type=int, default=16)
    ap.add_argument("--levels", type=int, default=2)
    ap.add_argument("--prior", default="auto")
    ap.add_argument("--max-iter", type=int, default=12)
    ap.add_argument("--gate", type=float, default=0.6, help="metres of path gated out (the wall's own return)")
    ap.add_argument("--init-fraction", type=float, default=0.25,
                    help="SurfaceSettings.init_fraction: the initialiser's support, hence the grid's extent")
    a = ap.parse_args(argv)
    path = data_dir() / "otoole2018_confocal" / a.file
    if not path.exists():
        print(f"{path} is absent: set STIRCASADI_DATA to the folder that holds otoole2018_confocal/")
        return 2
    t0 = time.perf_counter()
    est = estimate_capture(read_stanford_lct(path), method="surface", bin_factor=4, diffuse=bool(a.diffuse),
                           t_max=a.t_max, gate_m=a.gate, wall_step=a.wall_step, n_nodes=a.nodes, levels=a.levels,
                           max_iter=a.max_iter, prior=a.prior, init_fraction=a.init_fraction)
    dt = time.perf_counter() - t0
    s = est.surface
    row = {"file": a.file, "wall_step": a.wall_step, "traces": int(s.extras["n_traces"]), "nodes": a.nodes,
           "levels": a.levels, "prior": a.prior, "init_fraction": a.init_fraction, "gate_m": a.gate,
           "prior_weight": s.prior_weight,
           "albedo_prior": s.extras["albedo_prior"], "time_s": dt,
           "max_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20,
           "chi2_dof": s.chi2_dof, "mask_nodes": int(s.mask.sum()), "success": bool(s.success),
           "reasons": list(s.reasons)}
    print(json.dumps({k: v for k, v in row.items() if k != "reasons"}, default=float))
    for r in s.reasons:
        print("  reason:", r)
    out = ROOT / "benchmarks" / "results" / f"letters_{Path(a.file).stem}_{a.nodes}"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(row, indent=1, default=float))
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stircasadi.nlos.pictures import wall_view
    m = est.maps
    np.savez_compressed(out.with_suffix(".npz"), x=s.grid.x, y=s.grid.y, depth=s.depth, depth_std=s.depth_std,
                        albedo=s.albedo, albedo_std=s.albedo_std, mask=s.mask, edge=s.edge,
                        lct_x=m.x, lct_y=m.y, lct_albedo=m.albedo)
    fig, ax = plt.subplots(1, 4, figsize=(16, 4))
    wall_view(ax[0], m.albedo, m.x, m.y, cmap="gray")
    ax[0].set_title("LCT (initialiser) albedo")
    wall_view(ax[1], s.albedo, s.grid.x, s.grid.y, cmap="gray")
    ax[1].set_title(f"surface albedo, {a.nodes} x {a.nodes} nodes")
    wall_view(ax[2], np.where(s.mask, s.albedo, 0.0), s.grid.x, s.grid.y, cmap="gray")
    ax[2].set_title("surface albedo inside the mask")
    wall_view(ax[3], np.where(s.mask, s.depth, np.nan), s.grid.x, s.grid.y, cmap="viridis")
    ax[3].set_title("surface depth inside the mask (m)")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=80)
    print(f"written {out.with_suffix('.json')}, {out.with_suffix('.npz')} (the maps) and {out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
