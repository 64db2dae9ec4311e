"""Reflectance / joint-NLP benchmark: build and solve time and memory against patches and bins,
IPOPT (exact AD Hessian) vs Levenberg-Marquardt with the CasADi Jacobian vs LM with finite
differences, and what accuracy costs in time (bins, bounce order, solver tolerance).

Usage::

    python benchmarks/reflectance.py            # full sweep (a few minutes on 2 cores)
    python benchmarks/reflectance.py --quick    # small sweep (CI)

Prints tables and writes ``benchmarks/results/reflectance.json``. Each Lambertian-walls
configuration runs in a fresh subprocess on data simulated by the parent; its memory is the peak
resident memory (VmHWM, reset after loading the data) minus the resident memory at that point:
what building the model and NLP and solving with the three solvers add.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _rss_mb() -> float:
    """Peak resident memory (MB) since the last ``_reset_peak()`` (Linux VmHWM)."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _current_mb() -> float:
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return _rss_mb()


def _reset_peak() -> None:
    """Reset the peak-RSS mark (Linux >= 4.0: write 5 to /proc/self/clear_refs)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def numeric_lm_fd(nlp, scene, grid, sensor, bounces):
    """The baseline a MATLAB/scipy user gets: scipy LM with finite differences over the NUMERIC
    forward model (``stircasadi.transport.simulate``, path sums), same residual weights and
    support as the NLP. Returns (x, wall seconds, nfev)."""
    from scipy.optimize import least_squares

    from stircasadi.brdf import Lambertian
    from stircasadi.scene import Patch, Scene
    from stircasadi.transport import simulate

    m = nlp.model

    def resid(x):
        th = m.theta(x)
        pts = [Patch(tuple(th["position"][k]), p.normal, p.area, Lambertian(float(np.clip(th["albedo"][k], 0, 1))),
                     p.hidden, p.name) for k, p in enumerate(scene.patches)]
        sc = Scene(pts, source=scene.source, camera=scene.camera)
        y = simulate(sc, grid, sensor, method="bounces", bounces=bounces, allow_truncation=True).stir
        return nlp.w * (nlp.y - y.reshape(-1)[m.support])

    t0 = time.perf_counter()
    r = least_squares(resid, nlp.x0, jac="2-point", method="lm", xtol=1e-12, ftol=1e-12, gtol=1e-12)
    return r.x, time.perf_counter() - t0, r.nfev


def _walls_data(n_patches, n_bins, seed, path):
    """Simulate in the parent (the child's memory peak must be the estimator's alone)."""
    from stircasadi.problems import lambertian_walls as lw
    from stircasadi.transport import simulate

    sc, gr, se = lw.build_scene(n_patches), lw.build_grid(n_bins), lw.build_sensor(1e-2)
    cap = se.capture(simulate(sc, gr, se), seed=seed)
    np.savez(path, stir=cap.stir, sigma=cap.noise["sigma"])


def _walls_case(n_patches, n_bins, solvers, seed=1, q=None, data=None):
    import casadi  # noqa: F401  (imports before the baseline)
    from stircasadi.problems import lambertian_walls as lw
    from stircasadi.joint import EstimateSettings, JointNLP
    from stircasadi.model import TransientModel

    sc, gr, se = lw.build_scene(n_patches), lw.build_grid(n_bins), lw.build_sensor(1e-2)
    d = np.load(data)

    class cap:  # noqa: N801 - the two fields the NLP needs
        stir = d["stir"]
        noise = {"model": "gaussian", "sigma": float(d["sigma"])}
    _reset_peak()
    base = _current_mb()
    t0 = time.perf_counter()
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5).setup()
    nlp = JointNLP(m, cap.stir, EstimateSettings(), noise=cap.noise)
    t_build = time.perf_counter() - t0
    mem_build = _rss_mb() - base
    out = {"n_patches": n_patches, "n_bins": n_bins, "n_paths": m.info.n_paths,
           "n_residuals": m.info.n_support, "n_folded_residuals": int(nlp.r.shape[0]),
           "n_unknowns": m.n_x, "build_s": t_build,
           "build_mem_mb": mem_build, "solvers": {}}
    for name in solvers:
        st = EstimateSettings()
        st.ipopt.raise_on_failure = st.lm.raise_on_failure = False
        _reset_peak()
        before = _current_mb()
        if name == "lm-fd-numeric":
            nlp.settings = st
            x, wall, nfev = numeric_lm_fd(nlp, sc, gr, se, 2)
            err = m.theta(x)["albedo"] - sc.albedos
            out["solvers"][name] = {"wall_s": wall, "success": True, "iterations": nfev,
                                    "rms_albedo_error": float(np.sqrt(np.mean(err ** 2))),
                                    "solve_mem_mb": _rss_mb() - before}
            continue
        if name.startswith("lm"):
            st.lm.jacobian = name.split("-")[1]
            nlp.settings = st
            t1 = time.perf_counter()
            e = _solve(nlp, "lm")
        else:
            nlp.settings = st
            t1 = time.perf_counter()
            e = _solve(nlp, "ipopt")
        wall = time.perf_counter() - t1
        err = e.values["albedo"] - sc.albedos
        out["solvers"][name] = {"wall_s": wall, "success": e.success, "iterations": e.iterations,
                                "rms_albedo_error": float(np.sqrt(np.mean(err ** 2))),
                                "max_abs_z": float(np.max(np.abs(err / e.std["albedo"]))),
                                "solve_mem_mb": _rss_mb() - before}
    out["peak_mem_mb"] = _rss_mb() - base
    if q is not None:
        q.put(out)
    return out


def _corner_case(n_bins=1024, bounces=3, tol=1e-8, noise=1e-7, seed=4, q=None, solver="ipopt"):
    """Fig. 12's hidden corner: the two hidden positions (in the scene's plane, where their
    distances to the two visible patches fix them) and the four albedos jointly; the hidden
    starts put each distance 0.9-1.2 cm (about 2 bins of 5 mm) off."""
    import casadi  # noqa: F401
    from stircasadi.problems import hidden_corner as hc
    from stircasadi.joint import EstimateSettings, JointNLP
    from stircasadi.model import TransientModel
    from stircasadi.sensor import GaussianNoise, Sensor
    from stircasadi.timegrid import TimeGrid
    from stircasadi.transport import simulate

    sc = hc.build_scene()
    gr = TimeGrid(0.0, 5.12 / n_bins, n_bins)
    se = Sensor(irf=hc.build_sensor().irf, noise=GaussianNoise(relative=noise) if noise else None)
    cap = se.capture(simulate(sc, gr, se, bounces=3), seed=seed)
    t0 = time.perf_counter()
    m = TransientModel.from_scene(sc, gr, se.irf, bounces=bounces).set_unknown("albedo", initial=0.5)
    h = np.flatnonzero(sc.hidden)
    vis = np.flatnonzero(~sc.hidden)
    true_d = np.linalg.norm(sc.positions[h][:, None] - sc.positions[vis][None], axis=2)
    plane = np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])      # the scene's plane y = 0
    offs = np.array([[0.010, 0.0, -0.008], [-0.009, 0.0, 0.010]])
    for i, k in enumerate(h):
        m.set_unknown("position", [k], initial=sc.positions[k] + offs[i], lower=-0.03, upper=0.03,
                      scale=0.01, basis=plane)
    m.setup()
    st = EstimateSettings()
    st.ipopt.tol = tol
    st.ipopt.raise_on_failure = False
    nlp = JointNLP(m, cap.stir, st, noise=cap.noise)
    t_build = time.perf_counter() - t0
    x0 = m.x0
    d0 = np.abs(np.linalg.norm(m.theta(x0)["position"][h][:, None] - sc.positions[vis][None], axis=2) - true_d)
    t1 = time.perf_counter()
    if solver == "ipopt":
        e = _solve(nlp, "ipopt")
        th, iters, status = e.values, e.iterations, e.status
    elif solver in ("lm-ad", "lm-fd"):
        st.lm.jacobian = solver.split("-")[1]
        st.lm.raise_on_failure = False
        e = _solve(nlp, "lm")
        th, iters, status = e.values, e.iterations, e.status
    else:  # lm-fd-numeric
        x, _, iters = numeric_lm_fd(nlp, sc, gr, se, bounces)
        th, status = m.theta(x), "scipy lm"
    wall = time.perf_counter() - t1
    d_est = np.linalg.norm(np.asarray(th["position"])[h][:, None] - sc.positions[vis][None], axis=2)
    derr = np.abs(d_est - true_d).max()
    out = {"solver": solver, "n_bins": n_bins, "bounces": bounces, "tol": tol, "noise_rel": noise,
           "build_s": t_build, "solve_s": wall, "iterations": iters, "status": status,
           "start_distance_error_m": float(d0.max()),
           "max_distance_error_m": float(derr), "max_distance_error_bins": float(derr / gr.bin_width),
           "max_hidden_albedo_error": float(np.abs(th["albedo"][h] - sc.albedos[h]).max())}
    if q is not None:
        q.put(out)
    return out


def _solve(nlp, how):
    """One solve with the package's drivers (IPOPT or LM), assembled into values and stds."""
    from stircasadi.joint import assemble, solve_lm, solve_nlp

    sol = solve_nlp(nlp) if how == "ipopt" else solve_lm(nlp)
    return assemble(nlp, sol, list(nlp.model.names))


def _probe_case(hessian="exact", noise=0.0, n_bins=160):
    """The issue's probe: 9 patches, one hidden, hidden position + albedos jointly."""
    from stircasadi.problems import nine_patch_hidden as nine
    from stircasadi.joint import EstimateSettings, JointNLP
    from stircasadi.model import TransientModel
    from stircasadi.transport import simulate

    sc, gr, se = nine.build_scene(), nine.build_grid(n_bins), nine.build_sensor(noise)
    cap = se.capture(simulate(sc, gr, se), seed=3)
    h = 8
    p0 = sc.positions[h] + np.array([0.008, -0.006, 0.007])
    t0 = time.perf_counter()
    m = TransientModel.from_scene(sc, gr, se.irf).set_unknown("albedo", initial=0.5)
    m.set_unknown("position", [h], initial=p0, lower=-0.03, upper=0.03, scale=0.03).setup()
    st = EstimateSettings()
    st.ipopt.hessian = hessian
    st.ipopt.max_iter = 300
    st.ipopt.raise_on_failure = False
    nlp = JointNLP(m, cap.stir, st, noise=cap.noise)
    t_build = time.perf_counter() - t0
    t1 = time.perf_counter()
    e = _solve(nlp, "ipopt")
    wall = time.perf_counter() - t1
    d_est = np.linalg.norm(e.values["position"][h] - sc.positions[:8], axis=1)
    d_true = np.linalg.norm(sc.positions[h] - sc.positions[:8], axis=1)
    return {"hessian": hessian, "noise_rel": noise, "n_bins": n_bins, "build_s": t_build, "solve_s": wall,
            "iterations": e.iterations, "status": e.status,
            "max_distance_error_bins": float(np.abs(d_est - d_true).max() / gr.bin_width),
            "distance_std_bins": float(np.nanmax(e.std["position"][h]) / gr.bin_width),
            "max_albedo_error": float(np.abs(e.values["albedo"] - sc.albedos).max())}


def _isolated(fn, **kw):
    if fn is _walls_case:
        import tempfile
        path = Path(tempfile.mkdtemp()) / "walls.npz"
        _walls_data(kw["n_patches"], kw["n_bins"], kw.get("seed", 1), path)
        kw["data"] = str(path)
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=fn, kwargs={**kw, "q": q})
    p.start()
    import queue
    while True:  # a child that dies (killed, out of memory) must not hang the benchmark
        try:
            out = q.get(timeout=5)
            break
        except queue.Empty:
            if not p.is_alive():
                raise RuntimeError(f"the benchmark case {fn.__name__}({kw}) died with exit code "
                                   f"{p.exitcode} before reporting (killed, or out of memory?)")
    p.join()
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sweep for CI")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "reflectance.json"))
    a = ap.parse_args(argv)
    quick = a.quick
    patches = [10, 20] if quick else [10, 30, 50, 100]
    bins = [512, 1024] if quick else [512, 1024, 2048, 4096]
    res = {"patches": [], "bins": [], "accuracy": []}

    print("== Lambertian walls, 1 % noise: build and solve vs number of patches (1024 bins) ==")
    print("(resid: support bins; folded: residuals after the per-trace QR fold; bldMB: memory added by "
          "building model + NLP; ipMB: peak added by the IPOPT solve incl. uncertainty)")
    print(f"{'patches':>8}{'paths':>8}{'resid':>9}{'folded':>8}{'build s':>9}{'bldMB':>8}{'ipMB':>8}"
          f"{'ipopt s':>9}{'lm-ad s':>9}{'lm-fd s':>9}{'fdnum s':>9}{'fdnum/ip':>9}{'rms err':>10}{'fdnum err':>10}")
    for n in patches:
        solvers = ["ipopt", "lm-ad", "lm-fd"] + ["lm-fd-numeric"]
        r = _isolated(_walls_case, n_patches=n, n_bins=1024, solvers=solvers)
        res["patches"].append(r)
        s = r["solvers"]
        fdn = s.get("lm-fd-numeric")
        print(f"{n:>8}{r['n_paths']:>8}{r['n_residuals']:>9}{r['n_folded_residuals']:>8}{r['build_s']:>9.3f}{r['build_mem_mb']:>8.0f}{s['ipopt']['solve_mem_mb']:>8.0f}"
              f"{s['ipopt']['wall_s']:>9.3f}{s['lm-ad']['wall_s']:>9.3f}{s['lm-fd']['wall_s']:>9.3f}"
              + (f"{fdn['wall_s']:>9.2f}{fdn['wall_s'] / s['ipopt']['wall_s']:>9.0f}" if fdn else f"{'-':>9}{'-':>9}")
              + f"{s['ipopt']['rms_albedo_error']:>10.2e}"
              + (f"{fdn['rms_albedo_error']:>10.2e}" if fdn else f"{'-':>10}"))
        bad = [k for k, v in s.items() if not v["success"]]
        if bad:
            print(f"{'':>8}FAILED: {bad}")

    nb_p = 10 if quick else 30
    print(f"\n== Lambertian walls ({nb_p} patches): build and solve vs number of bins ==")
    print(f"{'bins':>8}{'resid':>9}{'folded':>8}{'build s':>9}{'bldMB':>8}{'ipMB':>8}{'ipopt s':>9}{'lm-ad s':>9}{'lm-fd s':>9}{'rms err':>10}")
    for nb in bins:
        r = _isolated(_walls_case, n_patches=nb_p, n_bins=nb, solvers=["ipopt", "lm-ad", "lm-fd"])
        res["bins"].append(r)
        s = r["solvers"]
        print(f"{nb:>8}{r['n_residuals']:>9}{r['n_folded_residuals']:>8}{r['build_s']:>9.3f}{r['build_mem_mb']:>8.0f}{s['ipopt']['solve_mem_mb']:>8.0f}"
              f"{s['ipopt']['wall_s']:>9.3f}{s['lm-ad']['wall_s']:>9.3f}{s['lm-fd']['wall_s']:>9.3f}"
              f"{s['ipopt']['rms_albedo_error']:>10.2e}")

    print("\n== Hidden corner (joint distances + albedos, IPOPT exact): accuracy vs time ==")
    print(f"{'solver':>14}{'bins':>6}{'K':>3}{'tol':>8}{'noise':>8}{'iter':>6}{'solve s':>9}{'dist err (bins)':>17}"
          f"{'dist err (m)':>14}{'alb err':>10}  status")
    cases = []
    for nb in ([512, 1024] if quick else [256, 512, 1024, 2048, 4096]):
        cases.append(dict(n_bins=nb, bounces=3, tol=1e-8, noise=1e-7))
    for K in ([2, 3] if quick else [2, 3, 4]):
        cases.append(dict(n_bins=1024, bounces=K, tol=1e-8, noise=1e-7))
    for tol in ([1e-2, 1e-8] if quick else [1e-1, 1e-2, 1e-4, 1e-6, 1e-8, 1e-10]):
        cases.append(dict(n_bins=1024, bounces=3, tol=tol, noise=0.0))
    for sv in ("lm-ad", "lm-fd", "lm-fd-numeric"):
        cases.append(dict(n_bins=1024, bounces=3, tol=1e-8, noise=1e-7, solver=sv))
    for c in cases:
        r = _corner_case(**c)
        res["accuracy"].append(r)
        print(f"{r['solver']:>14}{r['n_bins']:>6}{r['bounces']:>3}{r['tol']:>8.0e}{r['noise_rel']:>8.0e}{r['iterations']:>6}"
              f"{r['solve_s']:>9.3f}{r['max_distance_error_bins']:>17.2e}{r['max_distance_error_m']:>14.2e}"
              f"{r['max_hidden_albedo_error']:>10.2e}  {r['status']}")
    print("\n== Probe scene (9 patches, 1 hidden, 160 bins): hidden position + 9 albedos jointly ==")
    print("   (issue's probe floor, noise-free: 0.5 bin rounded delays, 0.1 linear, 0.006 Lanczos-4, "
          "2e-4 exact frequency-domain; L-BFGS ran out at 300 iterations)")
    print(f"{'hessian':>16}{'noise':>8}{'iter':>6}{'build s':>9}{'solve s':>9}{'dist err (bins)':>17}"
          f"{'pos std (bins)':>16}{'alb err':>10}  status")
    res["probe"] = []
    for hess in ("exact", "gauss-newton", "limited-memory"):
        for noise in ((0.0,) if quick else (0.0, 1e-6)):
            r = _probe_case(hess, noise)
            res["probe"].append(r)
            print(f"{hess:>16}{noise:>8.0e}{r['iterations']:>6}{r['build_s']:>9.3f}{r['solve_s']:>9.3f}"
                  f"{r['max_distance_error_bins']:>17.2e}{r['distance_std_bins']:>16.2e}"
                  f"{r['max_albedo_error']:>10.2e}  {r['status']}")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(res, indent=1))
    print(f"\nwrote {a.out}")


if __name__ == "__main__":
    main()
