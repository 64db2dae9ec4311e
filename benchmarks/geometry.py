"""Geometry benchmark: onset accuracy vs the Cramer-Rao bound, time against M and real scans.

Run:  python benchmarks/geometry.py      (prints tables, writes benchmarks/results/geometry.json)
SNR = 20 log10(peak of the pulse / noise std).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from stircasadi.geometry import distances as dm
from stircasadi.geometry import embedding as em
from stircasadi.geometry import onsets as on
from stircasadi.timegrid import TimeGrid

OUT = Path(__file__).resolve().parent / "results" / "geometry.json"
DATA = Path("/work/shared/data")


def onset_vs_crb(n_trials=400):
    grid = TimeGrid(0.0, 0.005, 400)
    tm = on.GaussTemplate(0.0267, 0.005)
    c = (np.arange(400) + 0.5) * 0.005
    rows = []
    rng = np.random.default_rng(0)
    for snr_db in (5, 10, 20, 30, 40):
        tau, amp = 1.00123, 1.0
        g, _ = tm.pulse(c - tau)
        peak = amp * g.max()
        sigma = peak / 10 ** (snr_db / 20)
        Y = amp * g[None] + rng.normal(0, sigma, (n_trials, 400))
        f = on.fit_onsets(Y, grid, tm, np.full(n_trials, tau), right_sigmas=4.0)
        err = f.tau[f.found] - tau
        crb = on.onset_crb(tm, amp, sigma, grid, tau)
        f15 = on.fit_onsets(Y, grid, tm, np.full(n_trials, tau), right_sigmas=1.5)
        e15 = f15.tau[f15.found] - tau
        rows.append({"snr_db": snr_db, "rmse_m": float(np.sqrt(np.mean(err ** 2))), "crb_m": crb,
                     "ratio": float(np.sqrt(np.mean(err ** 2)) / crb),
                     "ratio_window_1p5": float(np.sqrt(np.mean(e15 ** 2)) / crb),
                     "found_frac": float(f.found.mean())})
    return rows


def time_vs_M():
    rows = []
    rng = np.random.default_rng(1)
    for M in (10, 50, 100, 200):  # 500: > 5 min in the bounded refinement (see BENCHMARKS.md)
        Z = rng.uniform(-0.5, 0.5, (M, 3)) + np.array([0, 0, 1.5])
        r = np.linalg.norm(Z, axis=1)
        D = np.linalg.norm(Z[:, None] - Z[None], axis=2)
        O = dm.forward_T2(r, D)
        S = np.full_like(O, 1e-4)
        O = O + rng.normal(0, 1e-4, O.shape)
        t0 = time.perf_counter()
        sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
        t1 = time.perf_counter()
        X0, _ = em.classical_mds(sol.r, sol.D)
        t2 = time.perf_counter()
        X, info = em.refine_bounded(X0, sol.r, sol.r_std, sol.D, sol.D_std, sol.eps, sol.r_eps)
        t3 = time.perf_counter()
        U, _, Vt = np.linalg.svd(X.T @ Z)
        rmse = float(np.sqrt(np.mean(np.sum((X @ (U @ Vt) - Z) ** 2, axis=1))))
        rows.append({"M": M, "distances_s": t1 - t0, "mds_s": t2 - t1, "refine_s": t3 - t2,
                     "rmse_m": rmse, "refine_status": str(info.get("status"))})
    return rows


def real_scans():
    from stircasadi.acquisition import nlos_mat as nm
    from stircasadi.geometry import estimate_geometry
    rows = []
    for name in ("data_resolution_chart_40cm", "data_dot_chart_40cm", "data_exit_sign", "data_s_u"):
        f = DATA / "otoole2018_confocal" / f"{name}.mat"
        if not f.exists():
            continue
        t0 = time.perf_counter()
        cap = nm.read_stanford_lct(f)
        t1 = time.perf_counter()
        est = estimate_geometry(cap)
        t2 = time.perf_counter()
        rows.append({"scan": name, "shape": list(cap.traces.shape), "import_s": t1 - t0,
                     "estimate_s": t2 - t1, "depth_point_m": est.extras["depth_m"],
                     "depth_plane_m": est.extras["plane_depth_m"]})
    return rows


def main():
    res = {"onset_vs_crb": onset_vs_crb(), "time_vs_M": time_vs_M(), "real_scans": real_scans()}
    print("SNR dB | RMSE (m) | CRB (m) | ratio (window 4 sigma) | ratio (default 1.5 sigma)")
    for r in res["onset_vs_crb"]:
        print(f"{r['snr_db']:6d} | {r['rmse_m']:.3e} | {r['crb_m']:.3e} | {r['ratio']:.3f} | {r['ratio_window_1p5']:.3f}")
    print("M | distances s | MDS s | refine s | RMSE m")
    for r in res["time_vs_M"]:
        print(f"{r['M']} | {r['distances_s']:.3f} | {r['mds_s']:.3f} | {r['refine_s']:.3f} | {r['rmse_m']:.2e}")
    print("scan | shape | import s | estimate s | depth point m | depth plane m")
    for r in res["real_scans"]:
        print(f"{r['scan']} | {r['shape']} | {r['import_s']:.2f} | {r['estimate_s']:.2f} | "
              f"{r['depth_point_m']:.4f} | {r['depth_plane_m']:.4f}")
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
