"""Benchmark: the project's LCT, f-k and (filtered) backprojection against y-tal 0.20's f-k and
bp on the Stanford 40 cm charts, and the surface fit's time and memory against grid size. Prints
a table and writes benchmarks/results/nlos.json.

    PYTHONPATH=. <venv with y-tal>/bin/python benchmarks/nlos.py    # y-tal needs numpy < 2
    python benchmarks/nlos.py --no-ytal [--surface 8,16,32] [--charts resolution,dot]

Peak memory of the volumes is tracemalloc's peak of Python/NumPy allocations during the call
(y-tal and ours alike); the surface fit runs in its own process per grid size, timed without
tracemalloc, its memory the process's maximum resident set. Depth: median depth of the columns whose
volume maximum exceeds 30 % of the brightest (y-tal's volumes read with the same Maps code).
y-tal's bp is run on a 16 x 16 x 61 volume (2.4 GiB; its 32 x 32 x 121 volume needs ~15 GiB),
ours on the same grid and on 32 x 32 x 121 and 64 x 64 x 121. The surface fit runs on the
resolution chart (wall_step 4: 16 x 16 traces of 16 ps, the measured response and background
decay, Lambertian), coarse to fine from 8 x 8 nodes, with its Fisher std maps; ``--prior auto``
sets the smoothness prior's weight by the discrepancy principle (without a prior a 32 x 32 grid
over 16 x 16 traces is ill-posed). The fit runs on ``SurfaceSettings.threads`` threads (default:
the process's CPUs, at most 4, or 1 under OMP_NUM_THREADS=1; ``--threads``), ``--max-iter`` LM
iterations per level (default 12); each row records both. ``--albedo-prior A`` sets the albedo's
gradient penalty's relative weight under the chosen prior (``SurfaceSettings.albedo_prior``; default:
the fit's own, 1 with a prior; 0: free albedos);
``--no-quadrature-check`` keeps the size rule's sub-samples per cell (step 4d of the fit off):
the row records the sub-samples the fit ended with and each check of step 4d. ``--turn 90``
turns the wall's frame about its normal before the surface fit (results in nlos_turn90.json):
the same scan in another frame, where the plane and mask should not change.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from stircasadi.acquisition.importers import read_stanford_lct
from stircasadi.datasets import data_dir
from stircasadi.nlos import VolumeSettings, Volume, backprojection, estimate_capture, fk, from_capture, lct
from stircasadi.nlos.surface import SurfaceSettings
from stircasadi.nlos.surface.lm import last_decrease

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
    """y-tal's capture object for a confocal relay (t, x, y order), and our grid."""
    from stircasadi.nlos.confocal import prepare
    data, cg, w, gate = prepare(relay, VolumeSettings(bin_factor=factor))
    yy, xx = np.meshgrid(cg.y, cg.x, indexing="ij")
    grid = np.stack([xx, yy, np.zeros_like(xx)], axis=-1).transpose(1, 0, 2)  # (x, y, 3)
    H = np.ascontiguousarray(np.transpose(data.astype(np.float64), (2, 1, 0)))  # (t, x, y)
    try:
        from tal.enums import GridFormat, HFormat
        from tal.io.capture_data import NLOSCaptureData
    except ImportError:
        return SimpleNamespace(H=H, sensor_grid_xyz=grid, delta_t=w, is_confocal=lambda: True,
                               laser_grid_xyz=grid, t_start=0.0), cg, w
    d = NLOSCaptureData()
    d.H, d.H_format = H, HFormat.T_Sx_Sy
    d.sensor_grid_xyz = d.laser_grid_xyz = grid
    d.sensor_grid_format = d.laser_grid_format = GridFormat.X_Y_3
    nrm = np.zeros_like(grid)
    nrm[..., 2] = 1.0
    d.sensor_grid_normals = d.laser_grid_normals = nrm
    d.sensor_xyz = d.laser_xyz = np.array([0.0, 0.0, 1.0])
    d.delta_t, d.t_start, d.t_accounts_first_and_last_bounces = w, 0.0, False
    d.scene_info = {"is_confocal": True}
    return d, cg, w


def ytal_volume(vol_tyx, cg, w):
    M = vol_tyx.shape[0]
    return Volume(np.transpose(vol_tyx, (0, 2, 1)), cg.x, cg.y, (np.arange(M) + 0.5) * w / 2, cg.frame, "ytal")


def ytal_bp(cap, cg, n, nz):
    import tal.reconstruct.bp as bp
    from tal.enums import CameraSystem, VolumeFormat
    lin = np.linspace(cg.x[0], cg.x[-1], n)
    zs = np.linspace(0.2, 0.7, nz)
    V = np.stack(np.meshgrid(lin, lin, zs, indexing="ij"), axis=-1)
    out = np.asarray(bp.solve(cap, volume_xyz=V, volume_format=VolumeFormat.X_Y_Z_3,
                              camera_system=CameraSystem.DIRECT_LIGHT, progress=False))   # (x, y, z)
    return Volume(np.transpose(out, (2, 1, 0)).astype(np.float32), lin, lin, zs, cg.frame, "ytal-bp")


def turned(cap, deg: int):
    """``cap`` with its wall points turned by ``deg`` (a multiple of 90) about the wall's normal:
    the same scan in another frame, so a fit that depends only on the data gives the same plane."""
    if deg % 90:
        raise SystemExit(f"--turn must be a multiple of 90 degrees; got {deg}")
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][(deg // 90) % 4]
    for k in ("illuminated_xyz", "observed_xyz"):
        p = np.array(getattr(cap, k), float)
        p[:, :2] = np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1)
        setattr(cap, k, p)
    return cap


def surface_row(n: int, prior: str, threads: int | None = None, max_iter: int = 12,
                albedo_prior: float | None = None, quadrature_check: bool = True, turn: int = 0) -> dict:
    """The surface fit on the resolution chart, n x n nodes coarse to fine from 8 x 8: wall time,
    the process's maximum resident memory, the precision-weighted plane through the mask
    (``turn``: the wall's frame turned by that many degrees first)."""
    import resource

    cap = turned(read_stanford_lct(data_dir() / "otoole2018_confocal" / CHARTS["resolution"]), turn)
    levels = max(1, int(round(math.log2(n / 8))) + 1)
    t0 = time.perf_counter()
    est = estimate_capture(cap, method="surface", bin_factor=4, diffuse=False, t_max=1.6, gate_m=0.72,
                           wall_step=4, n_nodes=n, levels=levels, max_iter=max_iter, threads=threads,
                           prior=prior if prior in ("auto", "gcv", "none") else float(prior),
                           albedo_prior=albedo_prior, quadrature_check=quadrature_check)
    dt = time.perf_counter() - t0
    s = est.surface
    # weighted by the nodes' precision, 1 / depth std^2; no plane through fewer than 3 mask nodes
    z0, tilt = s.plane() if s.mask.sum() >= 3 else (None, None)
    return {"chart": "resolution", "method": f"surface {n}x{n}", "time_s": dt,
            "peak_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20, "peak_kind": "max RSS",
            "depth_m": z0, "tilt_deg": tilt, "chi2_dof": s.chi2_dof, "mask_nodes": int(s.mask.sum()),
            "depth_std_median_m": float(np.median(s.depth_std[s.mask])) if s.mask.any() else None,
            "prior": prior, "prior_weight": s.prior_weight, "turn_deg": turn,
            "prior_rejected": s.levels[-1].get("lambda_rejected"), "albedo_prior": s.extras["albedo_prior"], "success": s.success,
            "threads": SurfaceSettings(threads=threads).n_threads(), "max_iter": max_iter,
            "quadrature_check": quadrature_check, "subsamples": s.levels[-1]["subsamples"],
            "quadrature": s.levels[-1].get("quadrature"), "reasons": list(s.reasons),
            # steps 4b and 4c: nodes pruned, the centroids' test and what it was taken against
            "pruned": s.levels[-1].get("pruned"), "cut_cells": s.levels[-1].get("cut_cells"),
            "levels": [{"nodes": lv["nodes"], "iterations": [x["iterations"] for x in lv["solves"]],
                        "lam": [x["lam"] for x in lv["solves"]],
                        # chi^2 + prior removed by each solve's last step (>> 1: not converged)
                        "last_drop": [last_decrease(x) for x in lv["solves"]],
                        "status": [x["status"] for x in lv["solves"]],
                        "wall_time_s": lv["wall_time_s"]} for lv in s.levels]}


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--charts", default="resolution,dot")
    ap.add_argument("--no-ytal", action="store_true")
    ap.add_argument("--no-bp", action="store_true", help="skip the backprojections")
    ap.add_argument("--surface", default="8,16,32", help="surface grid sizes (nodes per side)")
    ap.add_argument("--prior", default="none", help="the surface fit's smoothness prior: none "
                    "(default), auto (discrepancy principle), gcv (generalised cross-validation), or a weight")
    ap.add_argument("--threads", type=int, default=None, help="the surface fit's threads (default: "
                    "SurfaceSettings.threads: the process's CPUs, at most 4; 1 under OMP_NUM_THREADS=1)")
    ap.add_argument("--max-iter", type=int, default=12, help="LM iterations per surface level")
    ap.add_argument("--albedo-prior", type=float, default=None, help="the surface fit's albedo_prior "
                    "(the albedo's gradient penalty relative to the depth's; needs --prior; default: "
                    "SurfaceSettings' own, 1 with a prior)")
    ap.add_argument("--no-quadrature-check", action="store_true", help="the surface fit keeps the "
                    "sub-samples of its size rule (SurfaceSettings.quadrature_check off): what the check costs")
    ap.add_argument("--turn", type=int, default=0, help="the surface fit's wall frame turned by this many "
                    "degrees (0, 90, 180, 270) about the wall's normal: the fit should not change")
    ap.add_argument("--surface-one", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.surface_one is not None:
        print(json.dumps(surface_row(a.surface_one, a.prior, a.threads, a.max_iter, a.albedo_prior,
                                     quadrature_check=not a.no_quadrature_check, turn=a.turn), default=float))
        return
    rows = []
    folder = data_dir() / "otoole2018_confocal"

    def bp_settings(n, nz):
        return VolumeSettings(bin_factor=4, n_lateral=n, z_range=(0.2, 0.7), n_depth=nz)

    for name in a.charts.split(","):
        f = folder / CHARTS[name]
        if not f.exists():
            print(f"skip {f}: absent")
            continue
        relay = from_capture(read_stanford_lct(f))
        st = VolumeSettings(bin_factor=4, diffuse=False)
        runs = [("lct 16ps", lambda: lct(relay, st)), ("fk 16ps", lambda: fk(relay, st))]
        if not a.no_bp:
            runs += [(f"fbp {n}x{n}x{nz}", (lambda n=n, nz=nz: backprojection(relay, bp_settings(n, nz))))
                     for n, nz in ((16, 61), (32, 121), (64, 121))]
        for label, fn in runs:
            vol, dt, gib = measure(fn)
            rows.append({"chart": name, "method": label, "time_s": dt, "peak_gib": gib, "depth_m": depth_of(vol)})
            print(rows[-1], flush=True)
        if not a.no_ytal:
            try:
                import tal.reconstruct.fk as tfk
            except ImportError as exc:
                print(f"y-tal not installed ({exc}); pip install y-tal==0.20 (numpy < 2)")
            else:
                cap, cg, w = ytal_capture(relay)
                v, dt, gib = measure(lambda: tfk.solve(cap))
                rows.append({"chart": name, "method": "y-tal fk 16ps", "time_s": dt, "peak_gib": gib,
                             "depth_m": depth_of(ytal_volume(np.asarray(v), cg, w))})
                print(rows[-1], flush=True)
                if not a.no_bp:
                    v, dt, gib = measure(lambda: ytal_bp(cap, cg, 16, 61))
                    rows.append({"chart": name, "method": "y-tal bp 16x16x61", "time_s": dt, "peak_gib": gib,
                                 "depth_m": depth_of(v)})
                    print(rows[-1], flush=True)
    f = folder / CHARTS["resolution"]
    if f.exists():
        for n in [int(x) for x in a.surface.split(",") if x]:
            # each size in its own process: the time without tracemalloc (which slows the fit's
            # many NumPy allocations several-fold) and the process's maximum resident memory
            # (CasADi's buffers included)
            out = subprocess.run([sys.executable, __file__, "--surface-one", str(n), "--prior", a.prior,
                                  "--max-iter", str(a.max_iter), "--turn", str(a.turn)]
                                 + ([] if a.albedo_prior is None else ["--albedo-prior", str(a.albedo_prior)])
                                 + (["--no-quadrature-check"] if a.no_quadrature_check else [])
                                 + ([] if a.threads is None else ["--threads", str(a.threads)]),
                                 capture_output=True, text=True)
            if out.returncode != 0:
                print(f"surface {n}x{n} failed:\n{out.stderr[-2000:]}")
                continue
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
    print(f"\n{'chart':<11}{'method':<20}{'time s':>9}{'peak GiB':>10}{'depth m':>10}")
    for r in rows:
        d = r["depth_m"]
        print(f"{r['chart']:<11}{r['method']:<20}{r['time_s']:>9.2f}{r['peak_gib']:>10.3f}"
              f"{(d if d is not None else float('nan')):>10.4f}")
    out = Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    (out / ("nlos.json" if not a.turn else f"nlos_turn{a.turn}.json")).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
