"""One study cell: build the scene, simulate it, estimate it blind, measure against the truth.

When to use
-----------
``run_cell(params)`` is what a Dask worker (or the serial runner) executes for each cell; it
never raises for a failure of the work (only for KeyboardInterrupt): the record says what
happened. It calls public entry points only -- ``stircasadi.transport.simulate``,
``Sensor.capture``, and the estimator through ``stircasadi.studies.adapter.run_estimate`` -- and
builds everything itself, so a cell depends on nothing but its parameters.

The record (a JSON-ready dict): ``params``; ``status`` (``ok``: an estimate came back;
``refused``: the estimator raised a ``StircasadiError`` -- a clear refusal; ``crashed``: it
raised anything else -- a bug; ``failed``: the cell could not be set up, simulated or
measured); ``stage`` and ``error`` where it stopped; ``measures`` (one flat dict: times, peak
memory, the simulation's choices, the estimate's verdict, checks, flags, iterations and the
comparison's summary); ``numbers`` (one row per reported number,
``stircasadi.testing.compare``).

The estimator gets the capture with its ``truth`` removed (a blind estimate); only the
measurement reads the truth.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import os
import platform
import threading
import time
import traceback

import numpy as np

from ..errors import StircasadiError, StudyError

__all__ = ["run_cell", "build_setup", "PeakMemory", "hard_verdict"]


class PeakMemory:
    """Peak resident memory of this process while the block runs (a sampling thread, every
    ``interval`` s; it sees NumPy and C++ (CasADi, IPOPT) allocations alike)."""

    def __init__(self, interval: float = 0.005):
        self.interval = interval
        self.baseline = self.peak = 0
        self._stop = threading.Event()

    def _rss(self) -> int:
        import psutil

        return psutil.Process().memory_info().rss

    def _run(self):
        while not self._stop.wait(self.interval):
            self.peak = max(self.peak, self._rss())

    def __enter__(self):
        self.baseline = self.peak = self._rss()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss())
        return False

    @property
    def peak_mb(self) -> float:
        return self.peak / 2 ** 20

    @property
    def delta_mb(self) -> float:
        return (self.peak - self.baseline) / 2 ** 20


# ---------------------------------------------------------------------------------- setup
def _call_with(fn, kwargs: dict, seed: int | None):
    sig = inspect.signature(fn)
    accepts_any = any(p.kind is p.VAR_KEYWORD for p in sig.parameters.values())
    kw = dict(kwargs)
    if seed is not None and ("seed" in sig.parameters or accepts_any) and "seed" not in kw:
        kw["seed"] = seed
    unknown = [k for k in kw if k not in sig.parameters and not accepts_any]
    if unknown:
        raise StudyError(f"{getattr(fn, '__qualname__', fn)} does not take {unknown}; it takes "
                         f"{list(sig.parameters)}. Fix scene_args / patches in the spec.")
    return fn(**kw)


def _import_callable(ref: str):
    import importlib

    mod_name, _, fn_name = ref.partition(":")
    if mod_name == "testing":
        mod_name = "stircasadi.testing.scenes"
    try:
        mod = importlib.import_module(mod_name)
    except ImportError as exc:
        raise StudyError(f"Scene generator module {mod_name!r} cannot be imported ({exc}); give "
                         "'package.module:function' importable on every worker.") from exc
    fn = getattr(mod, fn_name, None)
    if not callable(fn):
        raise StudyError(f"{mod_name} has no function {fn_name!r} (scene = {ref!r}).")
    return fn


def build_setup(params: dict):
    """(scene, grid, sensor, generator params) of a cell before any factor is applied."""
    args = dict(params.get("scene_args") or {})
    if "patches" in params:
        args["n_patches"] = int(params["patches"])
    if "problem" in params:
        from ..problem import load_problem

        mod = load_problem(params["problem"])
        scene = _call_with(mod.build_scene, args, None)
        return scene, mod.build_grid(), mod.build_sensor(), {}
    ref = params["scene"]
    if ref.startswith("hard:"):
        from .hardcases import build_hard_case

        return (*build_hard_case(ref[5:], **args), {})
    out = _call_with(_import_callable(ref), args, params.get("seed"))
    if isinstance(out, tuple) and len(out) == 3:
        return (*out, {})
    if all(hasattr(out, a) for a in ("scene", "grid", "sensor")):
        return out.scene, out.grid, out.sensor, dict(getattr(out, "params", {}) or {})
    raise StudyError(f"Scene generator {ref!r} returned {type(out).__name__}; it must return "
                     "(scene, grid, sensor) or an object with .scene, .grid and .sensor.")


def _apply_grid(grid, params):
    from ..timegrid import TimeGrid

    if "bin_width" in params or "bin_scale" in params:
        bw = float(params["bin_width"]) if "bin_width" in params else grid.bin_width * float(params["bin_scale"])
        n = int(math.ceil((grid.end - grid.start) / bw - 1e-9))
        grid = TimeGrid(start=grid.start, bin_width=bw, n_bins=n)
    if "n_bins" in params:
        grid = TimeGrid(start=grid.start, bin_width=grid.bin_width, n_bins=int(params["n_bins"]))
    return grid


def _apply_sensor(sensor, params):
    from ..irf import GaussianIRF, IdealIRF
    from ..sensor import GaussianNoise, PoissonNoise

    changes = {}
    irf = params.get("irf", "sensor")
    if irf == "ideal":
        changes["irf"] = IdealIRF()
    elif irf != "sensor":
        changes["irf"] = GaussianIRF.from_ps(float(irf))
    cal = params.get("calibrated_camera", "sensor")
    if cal != "sensor":
        changes["calibrated_camera"] = bool(cal)
    model = params.get("noise_model", "sensor")
    if model == "none":
        changes["noise"] = None
    elif "noise" in params:
        changes["noise"] = GaussianNoise(relative=float(params["noise"])) if params["noise"] > 0 else None
    elif "photons" in params:
        changes["noise"] = PoissonNoise(float(params["photons"]))
    elif "snr_db" in params:
        changes["noise"] = None  # set after the simulation, from the ideal peak
    return dataclasses.replace(sensor, **changes) if changes else sensor


def _simulate(scene, grid, sensor, params, m: dict):
    from ..sensor import GaussianNoise
    from ..transport import simulate
    from .effects import force, stir_change

    kw = {"method": params.get("method", "auto"), "delay_mode": params.get("delay_mode", "exact")}
    b = params.get("bounces", "auto")
    kw["bounces"] = None if b == "auto" else b
    effect, state = params.get("effect", "none"), params.get("effect_state", "auto")
    ref = None
    compared = effect != "none" and state != "auto"
    if compared:
        ref, m["sim_s_auto"] = _timed(lambda: simulate(scene, grid, sensor=sensor, **kw))
        scene, sensor, extra, m["effect_note"] = force(scene, sensor, effect, state)
        kw.update(extra)
    tr, m["simulate_s"] = _timed(lambda: simulate(scene, grid, sensor=sensor, **kw), repeat=compared)
    md = tr.metadata
    m.update({"sim_method": md.get("method"), "sim_bounces": str(md.get("bounces")),
              "sim_occlusion": str(md.get("occlusion")), "sim_glossy_terms": bool(md.get("glossy_terms")),
              "sim_irf": str(md.get("irf")), "omitted_energy_rel": md.get("omitted_energy_rel", float("nan")),
              "n_illuminated": int(md.get("n_illuminated", 0)), "n_observed": int(md.get("n_observed", 0)),
              "n_bins": grid.n_bins, "bin_width_m": grid.bin_width,
              "n_patches": scene.n_patches, "n_hidden_true": int(scene.hidden.sum())})
    if "snr_db" in params:
        peak = float(np.max(np.abs(tr.stir)))
        sensor = dataclasses.replace(sensor, noise=GaussianNoise(sigma=peak * 10 ** (-params["snr_db"] / 20)))
    drop = params.get("drop_direct")
    if drop is not None:
        tr = _drop_direct(tr, [drop] if isinstance(drop, int) else drop)
    if ref is not None:
        if effect == "noise":
            ref_cap = ref.capture(dataclasses.replace(sensor, noise=None), seed=params["seed"])
            cap = sensor.capture(tr, seed=params["seed"])
            change, note = float(np.max(np.abs(cap.stir - ref_cap.stir))), ""
        else:
            change, note = stir_change(ref, tr)
        peak = float(np.max(np.abs(ref.stir))) or float("nan")
        m["stir_change_rel"] = change / peak
        noise_std = sensor.noise.std(ref.stir) if isinstance(sensor.noise, GaussianNoise) else float("nan")
        m["stir_change_sigma"] = change / noise_std if noise_std > 0 else float("nan")
        if note:
            m["effect_note"] = (m.get("effect_note", "") + "; " + note).strip("; ")
    t = time.perf_counter()
    cap = sensor.capture(tr, seed=params["seed"])
    m["capture_s"] = time.perf_counter() - t
    m["noise_model"] = str(cap.noise.get("model"))
    m["noise_sigma"] = float(cap.noise.get("sigma", float("nan")))
    return cap


def _timed(fn, repeat: bool = True, short: float = 0.05):
    """(result, seconds); a run shorter than ``short`` s is repeated twice more and the fastest
    time kept (timer and cache noise dominate a millisecond simulation)."""
    t = time.perf_counter()
    out = fn()
    best = time.perf_counter() - t
    if repeat and best < short:
        for _ in range(2):
            t = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - t)
    return out, best


def _drop_direct(tr, ids):
    stir = np.array(tr.stir, copy=True)
    ill, obs = list(np.asarray(tr.ill_ids)), list(np.asarray(tr.obs_ids))
    for k in ids:
        if k not in ill or k not in obs:
            raise StudyError(f"drop_direct: patch {k} is not both illuminated and observed; the "
                             f"illuminated ids are {ill}, the observed {obs}.")
        stir[ill.index(k), obs.index(k), :] = 0.0
    return dataclasses.replace(tr, stir=stir)


# ---------------------------------------------------------------------------------- measures
def _estimate_measures(res_json: dict, info: dict) -> dict:
    stages = res_json.get("stages") or {}
    items = list(stages.values()) if isinstance(stages, dict) else list(stages)
    checks = res_json.get("checks") or []
    flags = sorted({str(f) for st in items if isinstance(st, dict) for f in (st.get("flags") or [])})
    iters = [st.get("iterations") for st in items if isinstance(st, dict) and isinstance(st.get("iterations"), int)]
    solver_iters = [st.get("iterations") for st in items if isinstance(st, dict) and st.get("solver")
                    and isinstance(st.get("iterations"), int)]
    return {"success": bool(res_json.get("success", False)), "verdict": res_json.get("verdict"),
            "frame": res_json.get("frame"),
            "reasons": "; ".join(map(str, res_json.get("reasons") or [])),
            "n_checks": len(checks), "checks_failed": ",".join(c.get("name", "?") for c in checks
                                                                if not c.get("passed", True)),
            "flags": ",".join(flags), "n_ambiguities": len(res_json.get("ambiguities") or []),
            "iterations": int(sum(iters)) if iters else 0,
            "solver_iterations": int(sum(solver_iters)) if solver_iters else 0,
            "stage_time_s": float(sum(st.get("wall_time_s") or 0.0 for st in items if isinstance(st, dict))),
            "n_patches_est": len(res_json.get("patches") or []),
            "n_hidden_est": sum(1 for p in res_json.get("patches") or [] if not p.get("visible", True)),
            **info}


def _describe_worst(comp) -> str:
    """The unflagged number furthest from the truth in sigma, in words."""
    w = comp.worst(1, unflagged_only=True)
    if not w:
        return ""
    r = w[0]
    std = "no std" if r["std_missing"] else f"std {r['std']:.2g}"
    name = r["quantity"] + (f".{r['component']}" if r["component"] else "")
    return (f"{'hidden' if not r['visible'] else 'visible'} patch {r['patch_id']} {name}: err "
            f"{r['err']:+.3g}, {std}, |err|/std {r['z']:.3g}")


def hard_verdict(status: str, m: dict, k: float = 4.0) -> str:
    """The hard-cases verdict of one cell (as ``blind_score.py``, plus missed hidden patches):
    REFUSED / CRASHED / FAILED / NOT-ESTIMATED / NON-FINITE / FLAGGED / SILENT-WRONG / MISSED / OK."""
    if status != "ok":
        return status.upper()
    if "success" not in m:
        return "NOT-ESTIMATED"
    if m.get("n_nonfinite", 0) > 0:
        return "NON-FINITE"
    if not m.get("success", False):
        return "FLAGGED"
    if m.get(f"n_beyond_{k:g}sigma_unflagged", 0) > 0:
        return "SILENT-WRONG"
    if m.get("n_missed", 0) > 0:
        return "MISSED"
    return "OK"


def run_cell(params: dict, sigma_limit: float = 4.0, keep_estimate: bool = False) -> dict:
    """Run one cell; see the module docstring for the record."""
    from .. import __version__
    from ..testing.compare import compare
    from .adapter import run_estimate

    m: dict = {}
    rec = {"params": params, "status": "failed", "stage": "setup", "error": None, "measures": m,
           "numbers": [], "worker": f"{platform.node()}:{os.getpid()}", "version": __version__}
    t0 = time.perf_counter()
    with PeakMemory() as mem:
        try:
            scene, grid, sensor, gen = build_setup(params)
            for k, v in gen.items():
                m[f"gen_{k}"] = v if isinstance(v, (int, float, str, bool)) or v is None else str(v)
            grid = _apply_grid(grid, params)
            sensor = _apply_sensor(sensor, params)
            rec["stage"] = "simulate"
            cap = _simulate(scene, grid, sensor, params, m)
            if params.get("estimate", True):
                rec["stage"] = "estimate"
                t = time.perf_counter()
                est_params = dict(params)
                if params.get("areas") == "truth":  # declared by the user, as --areas would
                    est_params["declared_areas"] = {int(i): float(cap.truth["areas"][i])
                                                    for i in np.asarray(cap.obs_ids)}
                try:
                    res, info = run_estimate(dataclasses.replace(cap, truth=None), est_params)
                finally:
                    m["estimate_s"] = time.perf_counter() - t
                rec["stage"] = "measure"
                js = res.to_json_dict()
                m.update(_estimate_measures(js, info))
                comp = compare(js, cap)
                m.update(comp.summary(k=sigma_limit))
                m["finite"] = comp.finite
                m["worst_unflagged"] = _describe_worst(comp)
                rec["numbers"] = comp.rows
                if keep_estimate:
                    rec["estimate"] = js
            rec["status"], rec["stage"] = "ok", "done"
        except (KeyboardInterrupt, SystemExit):
            raise
        except Exception as exc:  # recorded, never raised: one cell must not stop a study
            if rec["stage"] == "estimate":
                rec["status"] = "refused" if isinstance(exc, StircasadiError) else "crashed"
            rec["error"] = {"type": type(exc).__name__, "message": str(exc)[:2000],
                            "traceback": traceback.format_exc()[-3000:]}
    m["wall_s"] = time.perf_counter() - t0
    m["peak_rss_mb"], m["peak_rss_delta_mb"] = mem.peak_mb, mem.delta_mb
    m["hard_verdict"] = hard_verdict(rec["status"], m, sigma_limit)
    return rec
