"""Hidden surfaces by analysis by synthesis: a depth map and albedo per node fitted to the full
third-bounce transient (CasADi derivatives, Levenberg-Marquardt or IPOPT), coarse to fine, with
Fisher error bars.

When to use: after a volumetric reconstruction (its depth / albedo / mask maps initialise the
fit) on any relay: confocal or paired wall scans, or a full STIR's visible patches (Fig. 13).

Steps
-----
1. Initial surface: the volume's depth map where it holds a surface (its mask, or an albedo
   above ``init_fraction`` of the largest; the median of those depths elsewhere), its albedo
   map, resampled on a grid over that support's bounding box (``SurfaceSettings``).
2. Noise: the relay's sigma, Poisson weights 1 / max(y3, 1) for counts (y3: the counts
   averaged over 3 bins, which keeps the weights from favouring low fluctuations), or a MAD
   estimate.
3. Gain: with an unknown relay gain (real scans) one global factor scales the model to the data
   at the initial surface; albedos are then relative (``albedo_relative``).
4. Per level (coarse to fine, each started from the previous level's maps interpolated):
   the time window of the level's paths, then LM (``lm.py``) or IPOPT (``solve.py``) on the
   level's NLP. With ``prior="auto"`` the smoothness weight is chosen after each level's solve
   as the largest for which the whitened chi^2 of the linearised regularised solution stays
   within max(chi2_min, dof) (1 + 2 sqrt(2 / dof)) (discrepancy principle; ``_choose_lambda``);
   with ``prior="gcv"`` the same candidates are scored by generalised cross-validation instead
   (no noise level needed: ``_choose_lambda(rule="gcv")``); the penalty also holds the albedo's
   gradient, integral of |grad rho|^2, at relative weight ``albedo_prior`` (default 1; 0: none)
   (one weight for both: on the tilted-plane twin with 12 x 12 nodes over 8 x 8 traces the
   albedo error halves and the depth's weight drops 1 117 -> 35, its error 0.18 -> 0.46 mm);
   a coarse level's weight starts the next level (the penalty approximates the integral of
   (del^2 z)^2, independent of the spacing; the first level, solved without a prior, is solved
   again while its weight moves by more than 3x, up to ``FIRST_SOLVES`` solves: a weight chosen
   where an iteration limit cut the solve confirms itself), and the last level is re-solved when its weight
   moved by more than 3x (chosen at the level's start, from a chi^2 far above what it reaches,
   the weight came out too large: 32 x 32 tilt 10.8 against 2.4 deg on the resolution chart).
   A raised weight the data reject is not kept (``["lambda_rejected"]``, a note): where the
   model at its linearised step (``prior.step_chi2``), or else its solve, lands above the
   chi^2 its choice allowed (the step moves depths beyond the response's width), the level
   keeps the weight and solve before it (on the 32 x 32 chart weights of 4 006 after 45).
   4a. Depth steps (``SurfaceSettings.split_steps``, ``steps.py``): where the lit nodes fall
   into parts linked only by gentle slopes and two of them (at least 3 nodes and a quarter of
   the brightest part's summed albedo each) have a depth step between them, the grid takes
   separate height fields (``DepthGrid.labels``: no difference operator or prior crosses a
   label's border) and the last level is solved again from its solution, kept when its F ends
   lower (``levels[-1]["steps"]``; one field over two bars tilts their normals: seed 501).
   4b. Pruning (``SurfaceSettings.prune``, ``prune.py``): nodes whose albedo explains less of
   the data than noise would (each node's chi^2 rise without it, exact since the model is
   linear in the albedos, below the chi^2(2) quantile at p = 0.01) get albedo zero, held,
   and the last level is solved again from its solution, kept by a likelihood-ratio test
   (``levels[-1]["pruned"]``). Off-surface nodes that fit noise with barely determined depths
   had kept LM's steps in the response's nonlinear range (actual decrease 0.05-0.4 of the
   predicted) and 10 of 37 single-surface held-out scenes at the iteration limit. With 4c to
   follow, the pruned solve stops once its F is as low as the first solve's (the ratio at most 0:
   kept; only where the first solve stopped at its iteration limit) and 4c's solve goes on from
   there; it is solved on only where 4c's centroids are not kept.
   4c. Cut cells (``SurfaceSettings.edge_offsets``, ``cuts.py``): the last level is solved
   again with the cells the surface's edge cuts given a free in-plane centroid each, kept by a
   likelihood-ratio test (``levels[-1]["cut_cells"]``; against the pruned model's optimum
   estimated by the quadratic model where 4b stopped early, ``cuts.restricted_optimum``, and its
   settled solve where the estimate does not keep them). Seed 310 of the study (a square tilted
   20 deg, paired relay, 0.3 % noise): without, chi2/dof 1.034 and 16 of 38 claims beyond 2
   std, depths alternating row by row; with, 1.000 and 23 of 24 within 2 std. Where the
   centroids are kept, the cut cells' emitting parts may also get a free extent per side
   (``SurfaceSettings.edge_extent``): probed where the quadratic model at the centroids'
   solution passes the same test, kept where the probe does (``["cut_cells"]["extent"]``; ``edge_shear``: sheared).
   4d. Quadrature (``SurfaceSettings.quadrature_check``, ``quadrature.py``): while one more
   sub-sample per cell side changes a lit node's solution (to first order) by half its std or
   more, the level is solved again with it (up to 4 x 4, then a reason; ``["quadrature"]``).
   The result is the last level's: a coarser level cut by its iteration limit (or with a
   response parameter at a bound) is recorded in ``extras["notes"]``, not in ``reasons`` (the
   last level refits every unknown and is judged by its own solve and the checks below). The
   last level cut by its iteration limit is judged by its remaining undamped Gauss-Newton step
   (``lm.remaining_step``, ``extras["remaining_step"]``): a reason while it moves a mask node's
   depth or albedo by ``CONVERGED_STD`` (half) of its std or more, else a note (dark specks
   outside the mask that fit noise kept 7 of 14 held-out study scenes at the limit, their
   surfaces converged).
5. Covariance (H + lam R)^-1 from float64 products at the solution (R the prior's operator), std
   maps of depth, albedo and normals (``stdmaps.py``), inflated by sqrt(chi2/dof) when above 1;
   under a prior the maps are the data's, H^-1, unless ``claims_under_prior`` is "posterior". The
   mask keeps nodes whose albedo is above a tenth of the surface's bright one (``mask.bright_nodes``)
   and ``mask_z`` std above 0, on its own or as its 3 x 3 neighbourhood's mean (``mask.surface_mask``;
   under the albedo's prior with evidence of its own in the data). The edge map (``mask.edge_map``,
   ``SurfaceResult.edge``) marks the mask nodes whose cell the surface's edge may cut and their
   eight neighbours: each cell is modelled as uniformly covered, and where the edge cuts one its
   neighbours' albedos and depths trade with it, an error the Fisher std do not hold (a note in
   ``extras["notes"]``; the nodes' patches in estimate.json say so). Detection: the surface must lower
   the whitened chi^2 (divided by the inflation) below the no-surface model's (zero albedo) by
   more than the chi^2 quantile of 2 N degrees of freedom at p = ``DETECT_P`` (a likelihood
   ratio with every node's depth and albedo free); else the mask is empty, ``success`` false and
   ``reasons`` says "no surface detected" (``extras["detection"]``).
6. Explained returns (``explained.py``, ``SurfaceSettings.explained``): the chi^2 above is the
   fit's own time window's, around the surface it found; a surface in the wrong place leaves the
   real returns outside that window, or spread thinly over ~10^5 bins, and still reaches
   chi2/dof = 1.00 (measured on Fig. 13 at 1e-6: 14 mask nodes 0.6-2.4 m from the panel, no
   reason given before this check). The fitted model is evaluated over the relay's whole range
   after the gate, and a matched filter searches the whitened residual over explained_n^3 points
   (the relay's and the surface's bounding box grown by 0.5 m); a largest score above the noise
   level at p = ``explained_p`` (Bonferroni over the points) fails the fit with "unexplained
   returns" and the point (``extras["explained"]``).

Neglects what ``physics.py`` and ``response.py`` neglect; one background level for all bins.
"""
from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
from scipy.ndimage import binary_dilation, uniform_filter1d
from scipy.stats import chi2 as _chi2_dist

from ...errors import ReconstructionError
from ...progress import get_logger
from ..relay import Relay
from ..volume import Maps
from .grid import DepthGrid
from .start import extent as _extent, initial as _initial, response0 as _response0, window as _window
from .prior import GCV_PROBES, _choose_lambda, prior_operator, rejected, step_chi2  # noqa: F401  (read by the tests, patched by one)
from .cuts import CUT_P, cell_offsets, fit_cut_cells  # noqa: F401  (CUT_P: step 4c's test level, read here)
from .quadrature import refine_quadrature
from .prune import node_evidence, prune_nodes
from .stdmaps import data_covariance, gauss_newton_matrix, std_maps
from .steps import step_labels
from .lm import CONVERGED_STD, Bounds, last_decrease, prior_gradient, prior_vector, remaining_step, solve_lm
from .explained import explained_returns
from .model import SurfaceModel, SurfaceState
from .response import Response
from .mask import depth_step, edge_map, edge_note, edge_std, surface_mask
from .result import SurfaceResult
from .settings import SurfaceSettings
from .solve import solve_level

__all__ = ["fit_surface", "noise_weights", "DETECT_P", "FIRST_SOLVES"]

#: false-alarm probability of the surface detection test (step 5)
DETECT_P = 1e-3
#: with prior="auto" or "gcv", the most solves of the first (coarsest) level: it starts without
#: a prior, and its weight, chosen where its iteration limit cut the solve, confirms itself (a
#: large weight keeps the state far from the data's optimum, where no trusted step finds a lower
#: chi^2), so it is solved again from its solution while the weight moves by more than 3x. On the
#: real resolution chart (16 x 16 nodes over 16 x 16 traces, 12 iterations per solve) one solve
#: passed the next level a weight of 7 027 in one frame and 2 251 in the same frame turned by 90
#: deg (final weights 7 027 against 38, chi2/dof 4.87 against 3.02, 25 against 42 mask nodes);
#: with 3 solves 406 and 227 (final 40 against 23, 2.95 against 2.90, 44 against 40), 10 s more
FIRST_SOLVES = 3

_log = get_logger("stircasadi.nlos.surface")


def noise_weights(y: np.ndarray, sigma, override: float | None = None) -> tuple[np.ndarray, str]:
    """Inverse variances of the bins (and where they came from)."""
    if override is not None:
        return np.full(y.shape, 1.0 / override ** 2), "settings.noise_sigma"
    if sigma is not None and np.all(np.asarray(sigma) > 0):
        return np.broadcast_to(1.0 / np.asarray(sigma, float) ** 2, y.shape).copy(), "relay sigma"
    if np.all(y >= 0) and np.allclose(y, np.round(y)) and y.max() > 1:
        return 1.0 / np.maximum(uniform_filter1d(y, 3, axis=1), 1.0), "poisson (counts)"
    d = np.diff(y, axis=1).ravel()
    s = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
    s = max(s, 1e-6 * float(np.max(np.abs(y))), 1e-300)
    return np.full(y.shape, 1.0 / s ** 2), "MAD of first differences"


def fit_surface(relay: Relay, init: Maps, settings: SurfaceSettings | None = None,
                gate: float | None = None) -> SurfaceResult:
    """Fit a depth-map surface with albedo to ``relay``'s traces, starting from ``init`` maps.

    Parameters
    ----------
    relay : the traces and visible geometry (``stircasadi.nlos.relay``).
    init : depth / albedo / mask maps of a volumetric reconstruction in ``relay.frame``.
    settings : ``SurfaceSettings``.
    gate : earliest path length to model (the wall's own return lies before it).

    Returns
    -------
    SurfaceResult (never raises on a non-converged solve: ``success`` is False and ``reasons``
    says why).
    """
    st = (settings or SurfaceSettings()).validate()
    t_start = time.perf_counter()
    if relay.n_traces < 4:
        raise ReconstructionError(f"A surface fit needs at least 4 traces; got {relay.n_traces}.")
    r0, q_dir = _response0(relay, st, gate)
    w = relay.grid.bin_width
    slack = st.z_slack if st.z_slack is not None else 1.5 * max(w, r0.sigma)
    sig_b = (r0.sigma / 5.0, 5.0 * r0.sigma)
    tail_b = (0.02 * r0.sigma, min([40.0 * r0.sigma] + [0.5 * t for t, _ in r0.slow]))
    resp_hi = Response(r0.kind, 2.0 * r0.sigma, 2.0 * r0.tail if r0.kind == "emg" else 0.0)
    slow_pad = 0.5 * max([t for t, _ in r0.slow], default=0.0)
    ext = _extent(init, st)
    sizes = [max(4, int(round(st.n_nodes / 2 ** (st.levels - 1 - k)))) for k in range(st.levels)]
    frame = relay.frame
    dtype = np.float32 if st.step_precision == "float32" else np.float64
    chunk = int(st.chunk_mb * 2 ** 20)
    workers = st.n_threads()
    levels, reasons, notes = [], [], []
    pending = None     # the last level's iteration-limit message, judged in _finish
    lam = 0.0 if st.prior in ("auto", "gcv", "none") else float(st.prior)
    gain_scale = 1.0
    state = prev = None
    for li, n in enumerate(sizes):
        grid = DepthGrid.square(frame, ext[:2], ext[2:], n)
        if prev is None:
            z, rho = _initial(init, grid, st)
        else:
            z, rho = prev.resample(state.z, grid), np.clip(prev.resample(state.rho, grid), 0, None)
        last = li == len(sizes) - 1
        # coarse levels only start the next one: one moment-matched sample per cell
        sub = int(st.subsamples) if st.subsamples is not None else (int(
            min(2, max(1, math.ceil(max(grid.hx, grid.hy) / (2.0 * r0.sigma))))) if last else 1)
        cell = math.sqrt((grid.hx ** 2 + grid.hy ** 2) / 3.0) / sub
        rl = _window(relay, grid, z, resp_hi, cell, 4.0 * slack, gate, slow_pad)
        y = rl.traces
        wgt, noise_src = noise_weights(y, rl.sigma, st.noise_sigma)

        level = {"grid": grid}       # the level's grid (step 4a may label it)

        def make_model(nodes=None, rl=rl, sub=sub, extent=False):      # the level's model
            return SurfaceModel(level["grid"], rl, r0, st.brdf, st.fit_sigma, chunk, sub, q_dir, workers,
                                offset_nodes=nodes, cell_extent=extent, cell_shear=st.edge_shear)

        held = {"pruned": np.zeros(grid.n, bool)}       # step 4b's nodes, albedo held at zero

        def make_bounds(m):
            b = Bounds(m, 1.0 if st.known_gain else 1e3, sig_b, tail_b)
            b.hi[m.N:2 * m.N][held["pruned"]] = 0.0
            return b

        # the level's solver (``lin0``: LM's first linearisation; ``max_iter``: fewer than the level's)
        def solve(m, b, s0, lin0=None, f_stop=None, max_iter=None):
            it = st.max_iter if max_iter is None else min(int(max_iter), st.max_iter)
            if st.solver == "lm":
                return solve_lm(m, y, wgt, s0, lam, R, b, slack, it, st.tol, dtype, lin0=lin0,
                                tol_chi2=st.tol_chi2, f_stop=f_stop)
            return solve_level(m, y, wgt, s0, lam, R, b, it, st.tol)

        def record(res, **more):
            info["solves"].append({k: res[k] for k in ("status", "iterations", "success", "f", "at_bound", "history")
                                   if k in res}
                                  | {"lam": lam, "sigma": res["state"].sigma, "tail": res["state"].tail,
                                     "betas": list(res["state"].betas)} | more)

        if state is None:
            bg = float(np.percentile(y.mean(axis=0), 10)) if noise_src.startswith("poisson") else 0.0
            state = SurfaceState(z, rho, r0.sigma, r0.tail, tuple(b for _, b in r0.slow), bg)
            if q_dir is not None:
                state.bgtau = max(t for t, _ in r0.slow)
            m1 = make_model().predict(state) - bg
            s = float(np.sum(m1 * (y - bg)) / max(np.sum(m1 * m1), 1e-300))
            if not (s > 0):
                raise ReconstructionError("The initial surface predicts no signal where the data have "
                                          "it; check the relay geometry and the time window.")
            if st.known_gain:
                state.rho = np.clip(rho * s, 0.0, 1.0)
            else:
                gain_scale = s * max(float(rho.max()), 1e-12)
                state.rho = rho / max(float(rho.max()), 1e-12)
        else:
            state = replace(state, z=z, rho=rho)
        rl.gain = rl.gain * gain_scale
        model = make_model()
        bounds = make_bounds(model)
        R = prior_operator(grid, st)
        info = {"nodes": n, "rows": int(y.size), "traces": int(rl.n_traces), "subsamples": sub,
                "solves": []}
        t_lvl = time.perf_counter()
        auto = st.prior in ("auto", "gcv")
        lin = back = None
        # with a data-chosen weight the last level is solved again once where its weight moved by
        # more than 3x, and the first (coarsest) level up to FIRST_SOLVES times while it does (its
        # first solve has no prior: see FIRST_SOLVES)
        reps = (2 if last else FIRST_SOLVES if li == 0 else 1) if auto else 1
        for rep in range(reps):
            # a re-solve starts where the weight was chosen: that linearisation is its first step's
            res = solve(model, bounds, state, lin0=lin if rep else None)
            state = res["state"]
            record(res)
            _log.info("level %d (%dx%d) solve: %s, %d it, f=%.6g, lam=%.3g, sigma=%.4g, tail=%.4g",
                      li, n, n, res["status"], res["iterations"], res["f"], lam, state.sigma, state.tail)
            if not auto:
                break
            lin = model.linearise(state, y, wgt, dtype=np.float64)
            if rep and last and back is not None and lam > back["lam"] and lin["chi2"] > back["target"]:
                # the raised weight's solve ends above the chi^2 its choice allowed: the linearised
                # prediction it was chosen by does not hold (depth steps beyond the response's
                # width), so the data reject it and the level keeps the solve before it
                info["lambda_rejected"], note = rejected(li, n, lam, lin["chi2"], back["target"], back["lam"], True)
                notes.append(note)
                res, state, lin, lam = back["res"], back["state"], back["lin"], back["lam"]
                break
            dof = max(int(y.size) - model.npar, 1)
            ci = {}
            new_lam, curve = _choose_lambda(lin["H"], lin["g"], lin["chi2"], dof, R, grid.n, lam,
                                               prior_vector(state, R.shape[0]), 4.0 * slack, out_info=ci,
                                               rule="gcv" if st.prior == "gcv" else "discrepancy")
            info["lambda_curve"] = [(float(a), float(b)) for a, b in curve]
            step = ci.pop("step", None)
            info.setdefault("lambda_choice", []).append(ci | {"lam": float(new_lam)})
            moved = (new_lam > 3 * lam or new_lam < lam / 3) and not (new_lam == 0 and lam == 0)
            if last and moved and new_lam > lam and step is not None and rep + 1 < reps:
                # a raised weight is first tried on the model at its own linearised step: where
                # even that lands above the chi^2 the choice allowed, it is rejected unsolved
                c_step = step_chi2(model, state, bounds, step, y, wgt)
                info["lambda_choice"][-1]["chi2_step"] = c_step
                if c_step > ci["target"]:
                    info["lambda_rejected"], note = rejected(li, n, new_lam, c_step, ci["target"], lam, False)
                    notes.append(note)
                    break
            if not last:
                # the penalty sum (Lap z / h)^2 (Lap: unit-spacing stencil, ~ h^2 del^2 z) is the
                # integral of (del^2 z)^2 over the extent whatever the spacing, so a coarse
                # level's weight starts the next one
                # (a fine level solved without a prior is ill-posed: nodes the traces barely
                # separate trade depth against albedo and grow spikes)
                info["lam_next"] = float(new_lam)
            if moved and rep + 1 < reps:
                back = {"res": res, "state": state, "lin": lin, "lam": lam, "target": ci.get("target")}
                back = back if (last and back["target"] is not None) else None
                lam = new_lam
                continue
            if not last:
                lam = new_lam
            break
        if last and st.split_steps:
            # two surfaces side by side at different depths: separate height fields, the level
            # solved again from its solution, kept when its F ends lower (step 4a, ``steps.py``)
            lab = step_labels(grid.shape, state.z, state.rho, grid.hx, grid.hy)
            if lab is not None:
                level["grid"] = replace(grid, labels=lab)
                R0, R = R, prior_operator(level["grid"], st)
                m2 = make_model()
                b2 = make_bounds(m2)
                out = solve(m2, b2, state)
                kept = bool(out["f"] < res["f"])
                info["steps"] = {"parts": int(lab.max()) + 1, "labels": lab.tolist(), "f": float(out["f"]),
                                 "f_single": float(res["f"]), "kept": kept, "status": out["status"],
                                 "iterations": out["iterations"]}
                _log.info("level %d (%dx%d): split at a depth step: %d parts, F %.6g -> %.6g, kept %s",
                          li, n, n, info["steps"]["parts"], res["f"], out["f"], kept)
                if kept:
                    grid, model, bounds, res, lin = level["grid"], m2, b2, out, None
                    state = res["state"]
                    record(res, parts=info["steps"]["parts"])
                else:
                    level["grid"], R = grid, R0
        f_unpruned = res["f"]      # (the pruned model's optimum lies above this solve's: step 4c's floor)
        if last and st.prune:
            # nodes off the surface whose albedos fit noise: pruned and the level solved again
            # from its solution, kept by a likelihood-ratio test (step 4b, ``prune.py``)
            lin_p = lin if lin is not None else model.linearise(state, y, wgt, dtype=dtype)
            # (with step 4c to follow, the pruned solve stops once its F is the first solve's: 4c's
            # solve goes on from there, and the pruned one is settled only where 4c's are not kept)
            pr = prune_nodes(state, res, lin_p, y, wgt, model, lambda m: held.__setitem__("pruned", m),
                             make_bounds, solve, early=st.edge_offsets and st.solver == "lm")
            if pr is not None:
                info["pruned"] = pr["info"]
                _log.info("level %d (%dx%d): pruned %s", li, n, n, pr["info"])
                bounds = pr["bounds"]
                if pr["info"]["kept"]:
                    res, lin = pr["res"], None
                    state = res["state"]
                    record(res, pruned=int(pr["info"]["nodes"]))
        unsettled = bool(last and st.prune and pr is not None and pr["info"]["kept"] and not pr["info"]["settled"])
        pm = (model, bounds)

        def settle():          # step 4b's pruned solve, solved on from where it stopped
            out = solve(*pm, res["state"])
            record(out, pruned=int(pr["info"]["nodes"]), settled=True)
            return out
        if last and st.edge_offsets:
            # the cells the edge cuts emit from their covered part: their centroids become
            # unknowns and the level is solved again from its solution (step 4c, ``cuts.py``)
            cut = fit_cut_cells(grid.shape, state, res, y, wgt, make_model, make_bounds, solve,
                                settle=settle if unsettled else None,
                                quad={"lam": lam, "R": R, "dtype": dtype, "floor": f_unpruned}, extent=st.edge_extent)
            if cut is not None:
                info["cut_cells"] = cut["info"]
                _log.info("level %d (%dx%d): %s", li, n, n, cut["info"])
                if cut["restricted"] is not None:
                    res, unsettled = cut["restricted"], False
                    state = res["state"]
                if cut["info"]["kept"]:
                    model, bounds, res, lin, unsettled = cut["model"], cut["bounds"], cut["res"], None, False
                    state = res["state"]
                    record(res, offset_nodes=int(model.K))
        if unsettled:
            res = settle()
            state = res["state"]
        if last and st.quadrature_check:
            # is q x q sub-samples per cell fine enough for this noise? (step 4d, ``quadrature.py``)
            qd = refine_quadrature(state, res, model, bounds, y, wgt, lam, R, make_model, make_bounds, solve,
                                  z=st.mask_z)
            info["quadrature"] = qd["info"]
            for k, out in enumerate(qd["solves"]):
                record(out, subsamples=qd["info"][k]["q_next"], **({"offset_nodes": int(model.K)} if model.K else {}))
            if qd["solves"]:
                model, bounds, res, lin = qd["model"], qd["bounds"], qd["res"], None
                state = res["state"]
                info["subsamples"] = int(model.sub)
            if not qd["converged"]:
                reasons.append(f"level {li} ({n}x{n}): the cells' integration is not converged at {model.sub} x "
                               f"{model.sub} sub-samples (one more changes a lit node's solution by "
                               f"{qd['info'][-1]['max_std']:.3g} std): the numbers hold its error")
        info.update({"lam": lam, "status": res["status"], "success": res["success"],
                     "wall_time_s": time.perf_counter() - t_lvl})
        levels.append(info)
        # the result is the last level's state, judged by its own solve and checks; a coarser
        # level only starts the next one (as the volumetric initialiser does), so its iteration
        # limit or a response bound is a note, not a reason (the last level refits every unknown)
        said = reasons if last else notes
        if not res["success"]:
            drop = last_decrease(res)
            cut = drop is not None and res["status"].startswith("Maximum")
            tail = (f" (its last step still lowered the whitened chi2 plus prior by {drop:.4g}: not converged; "
                    "raise max_iter)") if cut else ""
            if not last:
                tail += "; a coarse level only starts the next one"
            msg = f"level {li} ({n}x{n}): solver status {res['status']}{tail}"
            if last and cut:
                pending = (msg, f"level {li} ({n}x{n}): stopped at its iteration limit (its last step lowered "
                                f"the whitened chi2 plus prior by {drop:.4g})")    # judged in _finish
            else:
                said.append(msg)
        if res["at_bound"]:
            said.append(f"level {li}: response parameter(s) {res['at_bound']} at their bounds "
                        f"(sigma in [{sig_b[0]:.3g}, {sig_b[1]:.3g}] m, tail in "
                        f"[{tail_b[0]:.3g}, {tail_b[1]:.3g}] m)")
        prev = grid
    # with prior="auto" the weight check after the last solve linearised at the final state (float64)
    return _finish(model, state, y, wgt, R, lam, st, levels, reasons, gain_scale, noise_src, rl,
                   relay.n_traces, t_start, (relay, gate, q_dir), lin, r0, notes, pending, bounds)


def _explained(model: SurfaceModel, state: SurfaceState, full, st: SurfaceSettings, gain_scale: float,
               also: np.ndarray) -> dict:
    """Step 6: the explained-returns check on the relay's whole time range after the gate."""
    relay, gate, q_dir = full
    lo = relay.grid.start if gate is None else max(float(gate), relay.grid.start)
    if relay.grid.end - lo < 2 * relay.grid.bin_width:
        return {"passed": True, "skipped": "no bins after the gate"}
    rf = relay.window(lo, relay.grid.end)
    rf.gain = rf.gain * gain_scale
    m_full = SurfaceModel(model.grid, rf, model.response(state), model.brdf, False, model.chunk_bytes,
                          model.sub, q_dir, model.workers, offset_nodes=model.onodes,
                          cell_extent=model.extent, cell_shear=model.shear)
    pred = m_full.predict(state)
    back = m_full.background(state)[0]
    wgt, _ = noise_weights(rf.traces, rf.sigma, st.noise_sigma)
    out = explained_returns(rf, rf.traces - pred, wgt, rf.traces - back, float(state.sigma), also=also,
                            p=float(st.explained_p), n=int(st.explained_n))
    out["window"] = [rf.grid.start, rf.grid.end]
    return out


def _finish(model, state, y, wgt, R, lam, st, levels, reasons, gain_scale, noise_src, rl, n_traces,
            t_start, full=None, lin=None, start=None, notes=None, pending=None, bounds=None) -> SurfaceResult:
    """Fisher covariance, std maps, mask, the checks and the result (see the module docstring,
    steps 5 and 6); ``lin``: a float64 linearisation at ``state`` already made, else one is;
    ``pending``: the last level's iteration-limit messages (reason, note), a reason unless the remaining
    Gauss-Newton step moves no mask node's depth or albedo by ``CONVERGED_STD`` of its std."""
    grid = model.grid
    notes = list(notes or [])
    if lin is None:
        lin = model.linearise(state, y, wgt, dtype=np.float64)
    H, chi2 = lin["H"], lin["chi2"]
    N = grid.n
    npar = H.shape[0]
    dof = max(int(y.size) - npar, 1)
    levels[-1]["chi2_dof"] = chi2 / dof
    A = gauss_newton_matrix(H, R, lam)
    C = np.linalg.inv(A)
    infl = max(1.0, chi2 / dof)
    z, rho = state.z, state.rho
    X, nrm, _ = grid.geometry(z)
    z_std, rho_std, n_std, gstd = std_maps(grid, C, infl, z, model.glob)     # the posterior's (no prior: H's)
    ap = bool(lam > 0 and st.albedo_weight() > 0)            # albedos under their smoothness prior
    data_claims = bool(lam > 0 and st.claims_under_prior == "data")
    # under the albedo's prior a mask node must also hold evidence of its own in the data (the
    # smoothing spreads albedo a node beyond the edge, where the posterior calls it significant)
    ev = node_evidence(rho, lin["g"][N:2 * N], np.diag(H)[N:2 * N]) / infl if ap and data_claims else None
    mask = surface_mask(grid, rho, rho_std, C[N:2 * N, N:2 * N] * infl, st.mask_z, evidence=ev)
    # detection: the surface must lower chi^2 below what the same window holds without it (zero
    # albedo, the fitted background and response) by more than chance would with 2 N free node
    # unknowns (likelihood ratio at p = DETECT_P, chi^2 scaled by the inflation); else the data
    # do not see a surface and the mask is empty
    chi2_0, _ = model.objective(replace(state, rho=np.zeros_like(state.rho)), y, wgt)
    gain_chi2 = (float(chi2_0) - chi2) / infl
    remaining = None
    if pending is not None:
        gt = prior_gradient(lin["g"], state, lam, R)
        remaining = remaining_step(model, state, A, gt, mask, z_std, rho_std, bounds)
        worst = remaining["max_std_mask"]
        remaining["converged"] = worst is not None and worst < CONVERGED_STD
        if remaining["converged"]:
            notes.append(f"{pending[1]}; the remaining Gauss-Newton step moves no mask node's depth or albedo by "
                         f"more than {worst:.2g} of its std (nodes outside the mask up to {remaining['max_std_any']:.3g}): "
                         "the surface's numbers are converged")
        else:
            reasons.append(pending[0] + ("" if worst is None else
                                      f"; the remaining Gauss-Newton step moves a mask node by {worst:.3g} std"))
    n_free = 2 * N + model.E * model.K       # the node unknowns (with any cut cells' centroids)
    need = float(_chi2_dist.isf(DETECT_P, n_free))
    detected = gain_chi2 > need
    if not detected:
        mask[:] = False
        reasons.append(f"no surface detected: the fitted surface lowers the whitened chi2 by {gain_chi2:.4g}, "
                       f"not more than the {need:.4g} that noise alone reaches with p = {DETECT_P:g} "
                       f"({n_free} free node unknowns); the mask is empty (more signal: longer exposure, "
                       "more traces)")
    explained = None
    if st.explained and full is not None:
        also = X[mask] if mask.any() else X
        explained = _explained(model, state, full, st, gain_scale, also)
        if not explained["passed"]:
            reasons.append(
                f"unexplained returns: the residual over the whole time window holds a return the "
                f"surface does not explain (matched-filter chi2 {explained['max_residual']:.4g} at "
                f"{np.round(explained['at'], 3).tolist()} m, above the {explained['threshold']:.4g} that "
                f"noise reaches with p = {explained['p']:g} over {explained['candidates']} candidate "
                f"points; the data's own largest is {explained['max_data']:.4g}): the surface may be "
                "in the wrong place or miss part of the scene, its error bars do not hold")
    shape = grid.shape
    edge = edge_map(mask.reshape(shape), rho.reshape(shape))
    # pruned nodes (step 4b) or at the albedo's bound 0, beside the mask: a zero held or censored at a bound
    # is no estimate the Fisher std hold (seed 1423: a node left dark inside a disk, 5.4 std off); edge numbers
    at0 = ((bounds.hi[N:2 * N] <= 0.0) | (rho <= bounds.lo[N:2 * N])) if bounds is not None else np.zeros(N, bool)
    held = at0.reshape(shape)
    held_edge = held & binary_dilation(mask.reshape(shape), structure=np.ones((3, 3), bool))
    edge = edge | held_edge
    step = depth_step(mask.reshape(shape), z.reshape(shape), z_std.reshape(shape), grid.hx, grid.hy,
                      labels=grid.labels)
    if step is not None:
        reasons.append(f"two surfaces side by side at different depths: nodes of two separate parts of the "
                       f"mask {step['distance']:.3g} m apart (two nodes or fewer) differ by {step['dz']:.3g} m "
                       f"in depth (slope {step['slope']:.2g}, beyond {step['limit']:g} after 3 std): the node between them "
                       "cannot take both depths, so the normals of one part tilt toward the other, an error "
                       "the std do not hold; fit each surface over its own extent (SurfaceSettings.extent)")
    if data_claims:     # the maps rest on the data, not the prior (stdmaps.py); the checks above read the posterior's
        z_std, rho_std, n_std, gstd = std_maps(grid, data_covariance(H), infl, z, model.glob)
    if edge.any():      # their std widened by the edge's model error (mask.edge_std), or said to hold noise only
        pb = ap and not data_claims             # the posterior's albedo std: the prior's bias needs the larger floor
        if st.edge_std_model:
            z_std, rho_std, n_std = edge_std(edge, mask, z_std, rho, rho_std, n_std, math.sqrt(grid.hx * grid.hy),
                                             prior=pb)
        notes.append(edge_note(int((edge & mask.reshape(shape)).sum()), int(mask.sum()), model, st.edge_std_model, pb))
    if held_edge.any():
        notes.append(f"{int(held_edge.sum())} node(s) beside the mask with a zero albedo (pruned, step 4b, or at the "
                     "albedo's bound) are marked in SurfaceResult.edge too: a zero held or censored at its bound is "
                     "not an estimate, and their Fisher std do not hold its error")
    if chi2 / dof > 1 + 5 * math.sqrt(2.0 / dof):
        reasons.append(f"whitened chi2/dof = {chi2 / dof:.3g} (the model leaves structure in the "
                       "residual; std inflated by sqrt(chi2/dof))")
    resp = model.response(state)
    r = lin["m"] - y
    return SurfaceResult(
        grid=grid, depth=z.reshape(shape), albedo=rho.reshape(shape), normals=nrm.reshape(shape + (3,)),
        depth_std=z_std.reshape(shape), albedo_std=rho_std.reshape(shape),
        normal_std=n_std.reshape(shape + (3,)), mask=mask.reshape(shape), edge=edge,
        edge_widened=bool(st.edge_std_model and edge.any()), sigma_irf=float(state.sigma),
        sigma_irf_std=gstd.get("sigma"), background=float(state.bg), gain=float(gain_scale),
        prior_weight=float(lam),
        prior_method={"auto": "discrepancy principle", "gcv": "generalised cross-validation",
                      "none": "none"}.get(st.prior, "fixed")
        if isinstance(st.prior, str) else "fixed",
        chi2_dof=float(chi2 / dof), dof=int(dof), albedo_relative=not st.known_gain,
        success=not reasons, levels=levels, wall_time_s=time.perf_counter() - t_start, reasons=reasons,
        response=resp.kind, tail=float(state.tail) if resp.kind == "emg" else None,
        tail_std=gstd.get("tail"), brdf=st.brdf, fwhm_irf=resp.fwhm(),
        extras={"noise": noise_src, "window": [rl.grid.start, rl.grid.end], "n_traces": n_traces,
                "response": resp.describe(), "background_std": gstd.get("bg"),
                # the response the fit started from (measured on the relay's direct return when
                # it holds one): an independent check of the fitted core
                "response_start": None if start is None else {"sigma": start.sigma, "tail": start.tail,
                                                              "describe": start.describe()},
                "detection": {"chi2_gain": gain_chi2, "threshold": need, "p": DETECT_P,
                              "detected": bool(detected)},
                "explained": explained,
                "depth_step": step,
                # a last level cut by its iteration limit: what the remaining Gauss-Newton step moves
                "remaining_step": remaining,
                # step 4c: the cut cells, their centroid offsets and any shrinks (``cuts.cell_offsets``)
                "cell_offsets": cell_offsets(model, state),
                # the albedo's gradient penalty's weight relative to the depth's (0: none)
                "albedo_prior": st.albedo_weight(),
                # what the std maps rest on (stdmaps.py): "fisher" (no prior), "data" or "posterior"
                "std_basis": "fisher" if lam <= 0 else ("data" if data_claims else "posterior"),
                # what the coarse levels could not do (not reasons: the last level decides)
                "notes": notes,
                # the last discrepancy choice (prior="auto"): its reference chi^2, target, whether
                # the slack bound it (then the weight reflects the solve's progress, not the noise)
                "prior_choice": next((lv["lambda_choice"][-1] for lv in reversed(levels)
                                      if lv.get("lambda_choice")), None),
                "slow_tails": [[t, b] for t, b in resp.slow],
                "background_decay": None if model.direct is None else
                {"amplitude": state.bg1, "length_m": state.bgtau},
                "residual_chi2_per_trace": (np.sum(wgt * r * r, axis=1)).tolist()
                if rl.n_traces <= 4096 else None})
