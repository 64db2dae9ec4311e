"""Applications benchmark: how far the applications' stated numbers can be trusted, and what
they cost.

* coverage of the propagated std of renders from the estimate (novel view, new source) over
  twin draws, and the linearised std against a Monte Carlo;
* segmentation: success rate against the albedo noise (three materials 0.2 apart, 15 patches)
  and the noise where it starts to fail;
* deconvolution of MLS codes: measured against stated rms error, against noise and code length;
* wall times of the commands' work (render with std, separation of a real 64 x 64 scan,
  deconvolution, FIR identification).

Usage::

    python benchmarks/apps.py            # full (a few minutes on 2 cores)
    python benchmarks/apps.py --quick    # fewer draws and seeds

Prints tables and writes ``benchmarks/results/apps.json``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def coverage(n_draws: int) -> dict:
    from stircasadi.apps.belief import SceneBelief
    from stircasadi.apps.render import RenderSettings, monte_carlo, render
    from stircasadi.apps.twin import estimate_from_scene
    from stircasadi.problems import hidden_corner

    scene, sensor = hidden_corner.build_scene(), hidden_corner.build_sensor()
    std = {"position": 0.003, "normal": 0.02, "area": 2e-4, "albedo": 0.02}
    truth = SceneBelief.from_estimate(estimate_from_scene(scene, std))
    out = {}
    for name, cfg in (("novel view (0, 0, 0.9)", {"camera": (0.0, 0.0, 0.9)}),
                      ("new source (0, 0.05, 0.9)", {"source": (0.0, 0.05, 0.9)})):
        ref = render(truth, sensor=sensor, settings=RenderSettings(with_std=False), **cfg)
        big = ref.stir > 0.05 * ref.stir.max()
        rng = np.random.default_rng(2024)
        zs, zb, t = [], [], time.perf_counter()
        for _ in range(n_draws):
            b = SceneBelief.from_estimate(estimate_from_scene(scene, std, rng=rng, correlation=0.2))
            r = render(b, grid=ref.grid, sensor=sensor, **cfg)
            zs.append(((r.steady - ref.steady) / r.steady_std).ravel())
            zb.append((r.stir - ref.stir)[big] / r.stir_std[big])
        dt = (time.perf_counter() - t) / n_draws
        zs, zb = np.concatenate(zs), np.concatenate(zb)
        r = render(truth, sensor=sensor, grid=ref.grid, **cfg)
        mc = monte_carlo(truth, 400, np.random.default_rng(3), grid=ref.grid, sensor=sensor, **cfg)
        out[name] = {"draws": n_draws, "coverage_steady_95": float(np.mean(np.abs(zs) < 1.96)),
                     "coverage_bins_95": float(np.mean(np.abs(zb) < 1.96)),
                     "z_std_steady": float(np.std(zs)), "z_std_bins": float(np.std(zb)),
                     "mc_over_linear_steady_median": float(np.median(mc["steady"] / r.steady_std)),
                     "render_with_std_s": dt, "n_renders": r.metadata["n_renders"]}
    return out


def segmentation(seeds: int) -> dict:
    from test_apps_segment import _rate, _scene

    scene, mats = _scene()
    rates = {s: _rate(s, seeds, scene, mats) for s in (0.01, 0.02, 0.03, 0.035, 0.04, 0.045, 0.05, 0.06, 0.08, 0.1)}
    onset = next((s for s, r in rates.items() if r < 0.9), None)
    return {"seeds": seeds, "rates": rates, "onset_sigma": onset}


def deconvolution(seeds: int) -> list:
    from stircasadi.apps.deconvolve import deconvolve, mls, simulate_records
    from stircasadi.problems import three_patch
    from stircasadi.timegrid import TimeGrid
    from stircasadi.transport import simulate

    scene, sensor = three_patch.build_scene(), three_patch.build_sensor()
    G = TimeGrid(1.7, 0.01, 160)
    h = simulate(scene, G, sensor=sensor, method="statespace", delay_mode="integer", allow_truncation=True).stir
    rows = []
    for order in (8, 10, 12, 14):
        for rel in (1e-4, 1e-3, 1e-2):
            meas, stated, ratio, t = [], [], [], 0.0
            for s in range(seeds):
                y = simulate_records(h, [mls(order)], rel * h.max(), np.random.default_rng(s))
                t0 = time.perf_counter()
                d = deconvolve(y, [mls(order)], G.n_bins, bin_width=G.bin_width, irf=sensor.irf)
                t += time.perf_counter() - t0
                err = np.sqrt(np.mean((d.h - h) ** 2, axis=-1))
                meas.append(np.sqrt(np.mean(err ** 2)) / h.max())
                stated.append(np.sqrt(np.mean(d.error_rms ** 2)) / h.max())
                ratio.append(err / d.error_rms)
            ratio = np.concatenate([r.ravel() for r in ratio])
            rows.append({"mls_order": order, "period": 2 ** order - 1, "noise_rel": rel,
                         "measured_rms_rel": float(np.mean(meas)), "stated_rms_rel": float(np.mean(stated)),
                         "ratio_min": float(ratio.min()), "ratio_max": float(ratio.max()),
                         "time_s": t / seeds})
    return rows


def timings() -> dict:
    from stircasadi.apps.belief import SceneBelief
    from stircasadi.apps.render import RenderSettings, render
    from stircasadi.apps.separate import separate_capture
    from stircasadi.apps.twin import estimate_from_scene
    from stircasadi.datasets import data_dir
    from stircasadi.problems import lambertian_walls

    out = {}
    b = SceneBelief.from_estimate(estimate_from_scene(lambertian_walls.build_scene(),
                                                      {"position": 0.002, "normal": 0.01, "area": 1e-5, "albedo": 0.01}))
    t = time.perf_counter()
    r = render(b, sensor=lambertian_walls.build_sensor(), settings=RenderSettings(bin_width=0.005))
    out["render with std, lambertian_walls (10 patches, 80 params)"] = {
        "s": time.perf_counter() - t, "n_renders": r.metadata["n_renders"], "bins": r.grid.n_bins}
    path = data_dir() / "otoole2018_confocal" / "data_dot_chart_40cm.mat"
    if path.exists():
        from stircasadi.acquisition.importers import read_stanford_lct
        cap = read_stanford_lct(path)
        t = time.perf_counter()
        separate_capture(cap)
        out["separate O'Toole dot chart (4096 x 2048, gate)"] = {"s": time.perf_counter() - t}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer draws and seeds")
    args = ap.parse_args(argv)
    res = {}
    res["coverage"] = coverage(20 if args.quick else 100)
    print("\nCoverage of the propagated std (95 % intervals), hidden_corner twin")
    print(f"{'configuration':<28}{'draws':>6}{'steady':>9}{'bins':>8}{'z std':>8}{'MC/lin':>8}{'s/render+std':>14}")
    for k, v in res["coverage"].items():
        print(f"{k:<28}{v['draws']:>6}{v['coverage_steady_95']:>9.3f}{v['coverage_bins_95']:>8.3f}"
              f"{v['z_std_steady']:>8.2f}{v['mc_over_linear_steady_median']:>8.2f}{v['render_with_std_s']:>14.3f}")
    res["segmentation"] = segmentation(10 if args.quick else 40)
    print("\nSegmentation: 3 materials (albedo 0.3/0.5/0.7) over 15 patches, alpha = 0.01")
    for s, r in res["segmentation"]["rates"].items():
        print(f"  albedo std {s:<6} correct {r:.2f}")
    print(f"  starts to fail (< 90 % correct) at albedo std {res['segmentation']['onset_sigma']}")
    res["deconvolution"] = deconvolution(2 if args.quick else 5)
    print("\nMLS deconvolution, three_patch (160 bins of 1 cm), GCV")
    print(f"{'order':>6}{'period':>8}{'noise':>9}{'measured':>11}{'stated':>10}{'ratio range':>16}{'time s':>9}")
    for r in res["deconvolution"]:
        print(f"{r['mls_order']:>6}{r['period']:>8}{r['noise_rel']:>9.0e}{r['measured_rms_rel']:>11.2e}"
              f"{r['stated_rms_rel']:>10.2e}{r['ratio_min']:>8.2f}-{r['ratio_max']:<7.2f}{r['time_s']:>9.3f}")
    res["timings"] = timings()
    print("\nWall times")
    for k, v in res["timings"].items():
        print(f"  {k}: {v}")
    out = ROOT / "benchmarks" / "results" / "apps.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2, default=float))
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
