"""Coverage study: does every reported std cover its error on scenes no one tuned the estimator on?

    python benchmarks/coverage.py [N_SCENES] [FIRST_SEED] [--timeout=S] [--workers=W] [--seeds=3,7,...]
                                  [--time-limit=S]

Draws scenes from the seeded generator (``stircasadi.testing.scenes.generate``), simulates each
through its sensor, estimates it BLIND (truth stripped) with ``stircasadi.pipeline.estimate_capture``
and scores it twice: ``stircasadi.report.compare`` (the blind_score rule, one row per vector) and
``stircasadi.testing.compare`` (one row per Gaussian number). Prints, and writes to
``benchmarks/results/coverage_<first>_<last>.json`` (or ``coverage_seeds_<first>.json``) after
every scene, each record with its estimate.json so the scoring can be recomputed:

* silent-wrong: estimates that report success with a number beyond 4 sigma or an error without
  a std (must be 0), by either scoring;
* coverage: the fraction of the estimated numbers of successful estimates (position and normal
  components in the truth's frame, albedo, area, albedo x area ...; given inputs, which carry no
  std and no error, left out) with |err|/sigma <= 1 (target 60-75 %) and <= 2 (target >= 93 %),
  overall and per quantity;
* hidden patches: for every true hidden patch of >= 2 cm whose third-bounce peak is >= 20 noise
  std, whether it was placed within 1 cm or the result was flagged;
* verdicts, wall times and failures (exceptions are recorded, never fatal).

``--time-limit=S`` gives every estimate that wall-clock limit (``estimate_capture(time_limit=)``:
a scene it cuts ends UNRELIABLE with the ``time-limit`` check failed, counted as
``n_time_limited``); ``--timeout`` still kills a scene that overruns it (checks and error bars of
a large model come after the limit).
"""
from __future__ import annotations

import json
import multiprocessing as mp
import sys
import time
import traceback
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"

def _hidden_visibility(g, cap):
    """Third-bounce peak / noise std of each hidden patch (simulated alone)."""
    from stircasadi.scene import Scene
    from stircasadi.transport import simulate

    sc = g.scene
    hid = np.flatnonzero(sc.hidden)
    out = {}
    for h in hid:
        keep = [k for k in range(sc.n_patches) if not sc.hidden[k] or k == h]
        s1 = Scene([sc.patches[k] for k in keep], source=sc.source, camera=sc.camera)
        tr = simulate(s1, g.grid, g.sensor_clean, bounces=3, per_bounce=True)
        out[int(h)] = float(tr.per_bounce[2].max() / g.sigma)
    return out

def one(seed: int, time_limit: float | None = None) -> dict:
    from stircasadi.pipeline import estimate_capture
    from stircasadi.progress import set_verbosity
    from stircasadi.report import compare, vec, alignment
    from stircasadi.testing.compare import compare as tcompare
    from stircasadi.testing.scenes import generate

    set_verbosity(-1)
    rec = {"seed": seed}
    try:
        g = generate(seed)
        rec["params"] = {k: (v if not isinstance(v, np.generic) else v.item()) for k, v in g.params.items()}
        cap = g.capture()
        truth = cap.truth
        cap.truth = None
        t0 = time.perf_counter()
        res = estimate_capture(cap, time_limit=time_limit)
        rec["wall_s"] = time.perf_counter() - t0
        d = res.to_json_dict()
        rec["verdict"] = d["verdict"]
        rec["reasons"] = d["reasons"]
        rows = compare(d, truth)
        rec["z"] = [(r["quantity"], None if r["z"] is None else float(r["z"])) for r in rows
                    if r["quantity"] != "match"]
        # coverage numbers: every estimated Gaussian number (position and normal components in
        # the truth's frame, scalars), given inputs (no std, exact) left out
        comp = tcompare(d, truth)
        rec["zc"] = [(r["quantity"], r["component"], bool(r["visible"]), float(r["z"]))
                     for r in comp.select()]
        rec["estimate"] = d                       # kept so any later scoring can be recomputed
        # hidden patches: placed within 1 cm of each true one?
        Q, s, st = alignment(d, truth)
        H = np.array([(vec(p.get("position")) - s) @ Q + st for p in d["patches"] if not p["visible"]
                      and p.get("position") is not None]).reshape(-1, 3)
        snr = _hidden_visibility(g, cap) if (~truth["visible"]).any() else {}
        hid = []
        for h, q in snr.items():
            side = float(np.sqrt(truth["areas"][h]))
            dmin = float(np.min(np.linalg.norm(H - truth["positions"][h], axis=1))) if len(H) else np.inf
            hid.append({"side": side, "snr": q, "dist": dmin})
        rec["hidden"] = hid
    except Exception as exc:  # recorded, never fatal
        rec["error"] = f"{type(exc).__name__}: {exc}"
        rec["trace"] = traceback.format_exc()[-1500:]
    return rec

def summarise(recs: list[dict]) -> dict:
    """Silent-wrong by the blind_score rule (any reported number, vector norms included, beyond
    4 sigma or without a std in a successful estimate); coverage over the Gaussian numbers of the
    successful estimates (``zc``: components and scalars with a std, given inputs left out; older
    records without ``zc`` fall back to the per-vector rows)."""
    ok = [r for r in recs if r.get("verdict") == "OK"]
    zl = [[z for *_, z in r["zc"]] if "zc" in r else [z for _, z in r.get("z", []) if z is not None]
          for r in ok]
    zs = np.array([z for zz in zl for z in zz if np.isfinite(z)])
    inf_z = sum(1 for zz in zl for z in zz if not np.isfinite(z))
    silent = [r["seed"] for r in ok if any(z is not None and (not np.isfinite(z) or z > 4)
                                           for _, z in r.get("z", []))
              or any(not np.isfinite(z) or z > 4 for *_, z in r.get("zc", []))]
    hid = [(h, r.get("verdict")) for r in recs for h in r.get("hidden", [])
           if h["side"] >= 0.02 and h["snr"] >= 20]
    hid_ok = sum(1 for h, v in hid if h["dist"] <= 0.01 or v != "OK")
    byq = {}
    for r in ok:
        for q, _, vis, z in r.get("zc", []):
            byq.setdefault(f"{q}{'' if vis else ' (hidden)'}", []).append(z)
    per_q = {q: {"n": len(v), "within_1sigma": float(np.mean(np.array(v) <= 1)),
                 "within_2sigma": float(np.mean(np.array(v) <= 2))} for q, v in sorted(byq.items())}
    return {"n_scenes": len(recs), "n_ok": len(ok), "per_quantity": per_q,
            "n_unreliable": sum(1 for r in recs if r.get("verdict") == "UNRELIABLE"),
            "n_error": sum(1 for r in recs if "error" in r),
            "n_time_limited": sum(1 for r in recs if any(str(x).startswith("time-limit")
                                                        for x in r.get("reasons", []))),
            "silent_wrong_seeds": silent, "n_numbers": int(len(zs) + inf_z), "n_infinite_z": inf_z,
            "within_1sigma": float(np.mean(zs <= 1)) if len(zs) else None,
            "within_2sigma": float(np.mean(zs <= 2)) if len(zs) else None,
            "hidden_visible": len(hid), "hidden_placed_or_flagged": hid_ok,
            "median_wall_s": float(np.median([r["wall_s"] for r in recs if "wall_s" in r])) if recs else None}

def _child(seed, conn, time_limit=None):
    conn.send(one(seed, time_limit))
    conn.close()


def _run_all(seeds, workers, timeout, time_limit=None):
    """Yield (seed, record) in seed order, each scene in its own process, at most ``workers`` at
    a time; a scene past ``timeout`` seconds is terminated (its record says so) so it cannot hold
    a worker and starve the scenes after it."""
    ctx = mp.get_context("spawn")
    pending, running, done = list(seeds), {}, {}
    order = list(seeds)
    while order:
        while pending and len(running) < workers:
            s = pending.pop(0)
            a, b = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_child, args=(s, b, time_limit), daemon=True)
            p.start()
            running[s] = (p, a, time.perf_counter())
        for s, (p, a, t) in list(running.items()):
            if a.poll():
                try:
                    done[s] = a.recv()
                except EOFError:
                    done[s] = {"seed": s, "error": "worker died (killed for memory?)"}
                p.join(5)
                del running[s]
            elif not p.is_alive():
                done[s] = {"seed": s, "error": f"worker died with exit code {p.exitcode} (killed for memory?)"}
                del running[s]
            elif time.perf_counter() - t > timeout:
                p.terminate()
                p.join(5)
                done[s] = {"seed": s, "error": f"timeout after {timeout:g} s"}
                del running[s]
        while order and order[0] in done:
            s = order.pop(0)
            yield s, done.pop(s)
        time.sleep(0.2)


def main(argv):
    args = [a for a in argv if not a.startswith("--")]
    n = int(args[0]) if args else 20
    first = int(args[1]) if len(args) > 1 else 0
    workers = int(next((a.split("=")[1] for a in argv if a.startswith("--workers=")), 1))
    timeout = float(next((a.split("=")[1] for a in argv if a.startswith("--timeout=")), 600))
    tl = next((a.split("=")[1] for a in argv if a.startswith("--time-limit=")), None)
    time_limit = float(tl) if tl not in (None, "0", "none") else None
    seeds = list(range(first, first + n))
    recs = []
    t0 = time.perf_counter()
    seeds_arg = next((a.split("=")[1] for a in argv if a.startswith("--seeds=")), None)
    if seeds_arg:  # an explicit list (e.g. re-running the scenes a change affects)
        seeds = [int(x) for x in seeds_arg.split(",") if x.strip()]
        first, n = seeds[0], 0
    for s, r in _run_all(seeds, workers, timeout, time_limit):
        recs.append(r)
        zmax = max([z for _, z in r.get("z", []) if z is not None] + [0])
        print(f"seed {s:4d} {r.get('params', {}).get('kind', '?'):6s} "
              f"cal={r.get('params', {}).get('calibrated', '?')!s:5s} "
              f"nvis={r.get('params', {}).get('n_visible', '?')!s:3s} nhid={r.get('params', {}).get('n_hidden', '?')} "
              f"{r.get('verdict', 'ERROR'):10s} max z {zmax:8.3g} {r.get('wall_s', 0):6.1f}s "
              f"{(r.get('error') or '; '.join(r.get('reasons', [])))[:110]}", flush=True)
        _write(first, n, recs, time.perf_counter() - t0, partial=True)  # nothing measured is lost
    summ = _write(first, n, recs, time.perf_counter() - t0, partial=False)
    print(json.dumps(summ, indent=1))
    return 0


def _write(first, n, recs, wall, partial):
    summ = summarise(recs)
    summ["wall_total_s"] = wall
    summ["partial"] = partial
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / (f"coverage_{first}_{first + n}.json" if n else f"coverage_seeds_{first}.json")
    tmp = out.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({"summary": summ, "records": recs}, default=str))
    tmp.replace(out)
    return summ

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
