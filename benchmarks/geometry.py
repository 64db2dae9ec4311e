"""Geometry benchmark: onset accuracy vs the Cramer-Rao bound, time against M and real scans.

Run:  python benchmarks/geometry.py [section ...]   (prints tables, writes
      benchmarks/results/geometry.json; sections: onset_vs_crb time_vs_M real_scans occluded;
      default all; a subset updates only its keys of an existing JSON)
SNR = 20 log10(peak of the pulse / noise std).
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from stircasadi.datasets import data_dir
from stircasadi.geometry import distances as dm
from stircasadi.geometry import embedding as em
from stircasadi.geometry import onsets as on
from stircasadi.timegrid import TimeGrid

OUT = Path(__file__).resolve().parent / "results" / "geometry.json"
DATA = data_dir()  # $STIRCASADI_DATA, default ../shared/data beside the repository


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


def _synthetic_stir(O, rng, n_bins=512, bin_width=0.012, snr_db=30.0):
    """A full STIR (M, M, n_bins) with one Gaussian-IRF pulse (std 0.0267 m of path, the 210 ps
    FWHM sensor of the paper, bin-integrated) at each onset O[i, j], peak 1, plus seeded white
    Gaussian noise of std 10^(-snr_db/20). Built row by row to keep temporaries at M x n_bins."""
    from stircasadi.capture import Capture

    M = O.shape[0]
    tm = on.GaussTemplate(0.0267, bin_width)
    start = float(np.floor((O.min() - 0.5) / bin_width) * bin_width)
    grid = TimeGrid(start, bin_width, n_bins)
    if O.max() + 0.3 > start + n_bins * bin_width:
        raise ValueError("time grid too short for the onsets")
    c = start + (np.arange(n_bins) + 0.5) * bin_width
    peak = float(tm.pulse(np.zeros(1))[0][0])
    sigma = 10 ** (-snr_db / 20)
    stir = np.empty((M, M, n_bins))
    for a in range(M):
        g, _ = tm.pulse(c[None, :] - O[a][:, None])
        stir[a] = g / peak + rng.normal(0.0, sigma, (M, n_bins))
    cap = Capture(grid=grid, stir=stir, noise={"model": "gaussian", "sigma": sigma})
    return cap, tm


def time_vs_M(Ms=(10, 50, 100, 200, 500)):
    """Seconds per geometry stage against the number of visible patches M (2-core CPU).

    Geometry stages on synthetic onsets (random patches in a 1 m cube 1.5 m from the co-located
    source/camera, true T2 onsets + N(0, (1e-4 m)^2), seeded); onset extraction timed separately
    on a synthetic STIR (``_synthetic_stir``) of the same scene, M^2 traces x 512 bins."""
    rows = []
    rng = np.random.default_rng(1)
    for M in Ms:
        Z = rng.uniform(-0.5, 0.5, (M, 3)) + np.array([0, 0, 1.5])
        r = np.linalg.norm(Z, axis=1)
        D = np.linalg.norm(Z[:, None] - Z[None], axis=2)
        O_true = dm.forward_T2(r, D)
        S = np.full_like(O_true, 1e-4)
        O = O_true + rng.normal(0, 1e-4, O_true.shape)
        t0 = time.perf_counter()
        sol = dm.solve_distances(np.arange(M), np.arange(M), O, S)
        t1 = time.perf_counter()
        X0, _ = em.embed(sol.r, sol.r_std, sol.D, sol.D_std)  # MDS + weighted LS, as estimate_geometry
        t2 = time.perf_counter()
        # as estimate_geometry does: bounds that hold jointly at the 99 % level
        kb = sol.joint_bound_scale()
        X, info = em.refine_bounded(X0, sol.r, sol.r_std, sol.D, sol.D_std, kb * sol.eps, kb * sol.r_eps)
        t3 = time.perf_counter()
        U, _, Vt = np.linalg.svd(X.T @ Z)
        rmse = float(np.sqrt(np.mean(np.sum((X @ (U @ Vt) - Z) ** 2, axis=1))))
        U0, _, Vt0 = np.linalg.svd(X0.T @ Z)
        rmse_mds = float(np.sqrt(np.mean(np.sum((X0 @ (U0 @ Vt0) - Z) ** 2, axis=1))))
        cap, tm = _synthetic_stir(O_true, np.random.default_rng(100 + M))
        t4 = time.perf_counter()
        _, _, O2, _, _ = on.second_onsets(cap, tm)
        t5 = time.perf_counter()
        err = O2 - O_true
        ok = np.isfinite(err)
        del cap
        rows.append({"M": M, "n_pairs": int(M * (M - 1) // 2), "onsets_s": t5 - t4,
                     "onset_rmse_m": float(np.sqrt(np.mean(err[ok] ** 2))),
                     "onset_found_frac": float(ok.mean()), "distances_s": t1 - t0, "mds_s": t2 - t1, "refine_s": t3 - t2,
                     "ipopt_s": float(sum(a["wall_time_s"] for a in info.get("attempts", []))),
                     "geometry_s": t3 - t0, "rmse_m": rmse, "rmse_mds_m": rmse_mds,
                     "refine_status": str(info.get("status")), "iterations": info.get("iterations"),
                     "bound_scale": kb,
                     "n_constraints": info.get("n_constraints"), "n_outside": info.get("n_outside"),
                     "widen": info.get("widen"),
                     "ipopt_attempts": [[a["return_status"], a["iterations"], round(a["wall_time_s"], 2)]
                                        for a in info.get("attempts", [])]})
        print(f"  M={M}: onsets {t5 - t4:.2f} s, geometry {t3 - t0:.2f} s", flush=True)
    return rows


def real_scans():
    from stircasadi.acquisition import importers as nm
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
    # CC-SOCR f-k statue (confocal) and general-NLOS tuan (paired): per-trace onsets (half path)
    for name, folder, reader in (("fk2019_statue", "fk2019_statue_confocal", nm.read_ccsocr),
                                 ("generalnlos2024_tuan", "generalnlos2024_tuan", nm.read_general_nlos)):
        f = DATA / folder
        if not f.exists():
            continue
        t0 = time.perf_counter()
        cap = reader(f)
        t1 = time.perf_counter()
        est = estimate_geometry(cap)
        t2 = time.perf_counter()
        o = est.extras["onsets"]
        half = o["tau"][o["used"]] / 2
        rows.append({"scan": name, "shape": list(cap.traces.shape), "import_s": t1 - t0,
                     "estimate_s": t2 - t1, "depth_point_m": est.extras["depth_m"],
                     "depth_plane_m": est.extras["plane_depth_m"],
                     "onset_half_path_p2_p20_p50_m": [float(np.percentile(half, q)) for q in (2, 20, 50)],
                     "n_traces_used": int(o["used"].sum()),
                     "tol_m": (cap.grid.bin_width + o["fwhm"]) / 2})
    return rows


def occluded(seeds=range(7), n_corrupt=8):
    """Fig. 13 (three planes, left panel behind a screen) at the problem's noise: visible RMSE after
    Procrustes per seed; and seed 0 with n_corrupt visible pairs whose O2_ij and O2_ji are both
    replaced by a copy 6 cm early (a return via a hidden patch), with and without the outlier screen
    (GeometrySettings.outlier_z = None)."""
    from stircasadi.geometry import estimate_geometry
    from stircasadi.errors import SolverError
    from stircasadi.geometry.estimate import GeometrySettings
    from stircasadi.report import position_rmse
    from stircasadi.problem import load_problem
    from stircasadi.transport import simulate

    mod = load_problem("three_planes_occluded")
    sc, g, se = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    tr = simulate(sc, g, sensor=se)
    rows = []
    for seed in seeds:
        cap = se.capture(tr, seed=seed)
        t0 = time.perf_counter()
        est = estimate_geometry(cap, hidden=0)
        rows.append({"case": "clean", "seed": int(seed), "rmse_m": position_rmse(est, cap.truth)[0],
                     "estimate_s": time.perf_counter() - t0, "widen": est.stats["refine"].extra["widen"],
                     "n_outliers": est.stats["refine"].extra.get("n_outliers", 0)})
    # lower noise (1e-7): the same-plane traces' third-bounce families are now detected and
    # stand in for ~30 % of the second onsets (SNR-seeded embedding, GeometrySettings)
    from stircasadi.irf import GaussianIRF
    from stircasadi.sensor import GaussianNoise, Sensor

    se7 = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(relative=1e-7))
    for seed in seeds:
        cap = se7.capture(tr, seed=seed)
        t0 = time.perf_counter()
        est = estimate_geometry(cap, hidden=0)
        split = est.stats.get("snr_split")
        n_drop = sum(len(a.get("pairs", [])) for a in est.ambiguities if a["kind"] == "outlier-distances")
        rows.append({"case": "noise 1e-7", "seed": int(seed), "rmse_m": position_rmse(est, cap.truth)[0],
                     "estimate_s": time.perf_counter() - t0, "widen": est.stats["refine"].extra["widen"],
                     "n_outliers": n_drop,
                     "snr_threshold": None if split is None else split.extra["threshold"],
                     "n_trusted": None if split is None else split.extra["n_trusted"]})
    for screen in (True, False):
        cap = se.capture(tr, seed=0)
        ill, obs = cap.ill_ids(), cap.obs_ids()
        rng = np.random.default_rng(5)
        wall, right = ill[ill < 49], ill[ill >= 98]
        for a, b in zip(rng.choice(wall, n_corrupt, replace=False), rng.choice(right, n_corrupt, replace=False)):
            for i, j in ((a, b), (b, a)):
                x, y = int(np.flatnonzero(ill == i)[0]), int(np.flatnonzero(obs == j)[0])
                cap.stir[x, y] = cap.stir[x, y] + np.roll(cap.stir[x, y], -6)
        t0 = time.perf_counter()
        case = f"{n_corrupt} pairs corrupted, screen {'on' if screen else 'off'}"
        try:
            est = estimate_geometry(cap, hidden=0, settings=GeometrySettings(outlier_z=8.0 if screen else None))
        except SolverError as exc:
            rows.append({"case": case, "seed": 0, "rmse_m": float("nan"), "estimate_s": time.perf_counter() - t0,
                         "widen": float("nan"), "n_outliers": 0, "failed": f"SolverError: {exc.status}"})
            continue
        rows.append({"case": case, "seed": 0,
                     "rmse_m": position_rmse(est, cap.truth)[0], "estimate_s": time.perf_counter() - t0,
                     "widen": est.stats["refine"].extra["widen"],
                     "n_outliers": est.stats["refine"].extra.get("n_outliers", 0)})
    return rows


def main(sections=None):
    funcs = {"onset_vs_crb": onset_vs_crb, "time_vs_M": time_vs_M, "real_scans": real_scans,
             "occluded": occluded}
    sections = list(sections or funcs)
    bad = [x for x in sections if x not in funcs]
    if bad:
        raise SystemExit(f"unknown section(s) {bad}; allowed: {list(funcs)}")
    res = json.loads(OUT.read_text()) if OUT.exists() and len(sections) < len(funcs) else {}
    res.update({k: funcs[k]() for k in sections})
    if "onset_vs_crb" in sections:
        print("SNR dB | RMSE (m) | CRB (m) | ratio (window 4 sigma) | ratio (default 1.5 sigma)")
        for r in res["onset_vs_crb"]:
            print(f"{r['snr_db']:6d} | {r['rmse_m']:.3e} | {r['crb_m']:.3e} | {r['ratio']:.3f} | {r['ratio_window_1p5']:.3f}")
    if "time_vs_M" in sections:
        print("M | onsets s (M^2 x 512 bins) | distances s | embed s (MDS + LS) | refine s (IPOPT s) | geometry s | "
              "RMSE embed m | RMSE refined m | IPOPT iter / constraints / outside / widen")
        for r in res["time_vs_M"]:
            print(f"{r['M']} | {r['onsets_s']:.2f} | {r['distances_s']:.3f} | {r['mds_s']:.3f} | "
                  f"{r['refine_s']:.2f} ({r['ipopt_s']:.2f}) | {r['geometry_s']:.2f} | {r['rmse_mds_m']:.2e} | "
                  f"{r['rmse_m']:.2e} | {r['iterations']} / {r['n_constraints']} / {r['n_outside']} / x{r.get('widen', 1):g}")
    if "real_scans" in sections:
        print("scan | shape | import s | estimate s | depth point m | depth plane m | onset p2/p20/p50 m | tol m")
        for r in res["real_scans"]:
            extra = (" | " + "/".join(f"{v:.3f}" for v in r["onset_half_path_p2_p20_p50_m"]) + f" | {r['tol_m']:.4f}"
                     if "onset_half_path_p2_p20_p50_m" in r else "")
            print(f"{r['scan']} | {r['shape']} | {r['import_s']:.2f} | {r['estimate_s']:.2f} | "
                  f"{r['depth_point_m']:.4f} | {r['depth_plane_m']:.4f}{extra}")
    if "occluded" in sections:
        print("case | seed | visible RMSE m | estimate s | widen | outliers dropped")
        for r in res["occluded"]:
            print(f"{r['case']} | {r['seed']} | {r['rmse_m']:.3e} | {r['estimate_s']:.1f} | {r['widen']:g} | "
                  f"{r['n_outliers']}" + (f" | {r['failed']}" if r.get("failed") else ""))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
