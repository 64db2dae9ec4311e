"""Benchmark: the project's LCT, f-k and (filtered) backprojection against y-tal 0.20's f-k
(and optionally bp) on the Stanford 40 cm charts, and the surface fit's time and memory against
grid size. Prints a table and writes benchmarks/results/nlos.json.

    python benchmarks/nlos.py [--ytal-bp] [--surface 8,16,32] [--charts resolution,dot]

Peak memory is tracemalloc's peak of Python/NumPy allocations during the call (y-tal and ours
alike). Depth: median depth of the columns whose volume maximum exceeds 30 % of the brightest
(y-tal's volume read with the same Maps code). y-tal is the ``bench`` extra (pip y-tal).
"""
from __future__ import annotations

import argparse
import json
import time
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from stircasadi.acquisition.nlos_mat import read_stanford_lct
from stircasadi.datasets import data_dir
from stircasadi.nlos import VolumeSettings, Volume, backprojection, estimate_capture, fk, from_capture, lct

CHARTS = {"resolution": "data_resolution_chart_40cm.mat", "dot": "data_dot_chart_40cm.mat"}


def measure(fn):
    tracemalloc.start()
    t0 = time.perf_counter()
    out = fn()
    dt = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return out, dt, peak / 2 ** 30


def depth_of(vol: Volume) -> float:
    m = vol.maps(z_min=0.2)
    sel = m.albedo > 0.3
    return float(np.median(m.depth[sel]))


def ytal_capture(relay, factor=4):
    from stircasadi.nlos.confocal import prepare
    data, cg, w, gate = prepare(relay, VolumeSettings(bin_factor=factor))
    N = data.shape[0]
    yy, xx = np.meshgrid(cg.y, cg.x, indexing="ij")
    grid = np.stack([xx, yy, np.zeros_like(xx)], axis=-1).transpose(1, 0, 2)  # (x, y, 3)
    H = np.ascontiguousarray(np.transpose(data.astype(np.float64), (2, 1, 0)))  # (t, x, y)
    return SimpleNamespace(H=H, sensor_grid_xyz=grid, delta_t=w, is_confocal=lambda: True,
                           laser_grid_xyz=grid, t_start=0.0), cg, w


def ytal_volume(vol_tyx, cg, w):
    M = vol_tyx.shape[0]
    return Volume(np.transpose(vol_tyx, (0, 2, 1)), cg.x, cg.y, (np.arange(M) + 0.5) * w / 2, cg.frame, "ytal")


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--charts", default="resolution,dot")
    ap.add_argument("--ytal-bp", action="store_true", help="also run y-tal's bp (15 GiB, minutes)")
    ap.add_argument("--no-ytal", action="store_true")
    ap.add_argument("--no-bp", action="store_true", help="skip our backprojection (minutes on 2 cores)")
    ap.add_argument("--surface", default="8,16", help="surface grid sizes (nodes per side)")
    a = ap.parse_args(argv)
    rows = []
    folder = data_dir() / "otoole2018_confocal"
    for name in a.charts.split(","):
        f = folder / CHARTS[name]
        if not f.exists():
            print(f"skip {f}: absent")
            continue
        relay = from_capture(read_stanford_lct(f))
        st = VolumeSettings(bin_factor=4, diffuse=False)
        for label, fn in (("lct 16ps", lambda: lct(relay, st)), ("fk 16ps", lambda: fk(relay, st)),
                          ("fbp 32x32", lambda: backprojection(relay, VolumeSettings(
                              bin_factor=4, n_lateral=32, z_range=(0.2, 0.7), n_depth=121))),
                          ("fbp 64x64", lambda: backprojection(relay, VolumeSettings(
                              bin_factor=4, n_lateral=64, z_range=(0.2, 0.7), n_depth=121)))):
            if a.no_bp and label.startswith("fbp"):
                continue
            vol, dt, gib = measure(fn)
            rows.append({"chart": name, "method": label, "time_s": dt, "peak_gib": gib, "depth_m": depth_of(vol)})
            print(rows[-1], flush=True)
        if not a.no_ytal:
            try:
                import tal.reconstruct.fk as tfk
            except ImportError as exc:
                print(f"y-tal not installed ({exc}); pip install y-tal==0.20")
            else:
                cap, cg, w = ytal_capture(relay)
                v, dt, gib = measure(lambda: tfk.solve(cap))
                rows.append({"chart": name, "method": "y-tal fk 16ps", "time_s": dt, "peak_gib": gib,
                             "depth_m": depth_of(ytal_volume(np.asarray(v), cg, w))})
                print(rows[-1], flush=True)
    cap = read_stanford_lct(folder / CHARTS["resolution"]) if (folder / CHARTS["resolution"]).exists() else None
    if cap is not None:
        for n in [int(x) for x in a.surface.split(",") if x]:
            est, dt, gib = measure(lambda: estimate_capture(
                cap, method="surface", bin_factor=4, diffuse=False, wall_step=max(1, 64 // (2 * n)),
                n_nodes=n, levels=1, t_max=1.2, max_iter=15))
            s = est.surface
            rows.append({"chart": "resolution", "method": f"surface {n}x{n}", "time_s": dt, "peak_gib": gib,
                         "depth_m": float(np.median(s.depth[s.mask])) if s.mask.any() else None,
                         "chi2_dof": s.chi2_dof, "success": s.success})
            print(rows[-1], flush=True)
    print(f"\n{'chart':<11}{'method':<16}{'time s':>9}{'peak GiB':>10}{'depth m':>10}")
    for r in rows:
        d = r["depth_m"]
        print(f"{r['chart']:<11}{r['method']:<16}{r['time_s']:>9.2f}{r['peak_gib']:>10.3f}"
              f"{(d if d is not None else float('nan')):>10.4f}")
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / "nlos.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
