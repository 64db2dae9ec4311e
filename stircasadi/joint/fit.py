"""The joint fit: known patches first, then hidden patches added while the data ask for them.

1. Fit the visible patches (``policy.plan_model`` with no hidden patch) to the whole STIR.
2. Search the whitened residual for the best hidden point (``search.search``), add a hidden
   patch there, refit everything, and keep it when the whitened chi2 drops by more than the
   chi-square quantile of 1 - ``search.p_value`` for the unknowns it adds (a likelihood-ratio
   test); repeat. ``n_hidden`` (``--hidden N``) fixes the number instead.
3. The last accepted model is the estimate: ``result.assemble`` gives every number with its
   Cramér-Rao std (inflated by sqrt(chi2/dof) on a mismatch) and identifiability.

The noise level is the capture's when given and consistent with the data's off-model bins
(else the larger of the two, noted), or estimated from the data.
"""
from __future__ import annotations

import contextlib

import copy
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..errors import SolverError
from ..progress import get_logger
from .budget import WALL_TIME_STATUS, Budget
from .lm import solve_lm
from .nlp import JointNLP
from .policy import HiddenStart, VisibleStart, plan_model
from .result import assemble
from .search import search
from .solve import Solution, solve_nlp

__all__ = ["FitResult", "fit_joint", "fit_model", "noise_level", "lr_threshold"]

log = get_logger(__name__)


@dataclass
class FitResult:
    estimate: object
    plan: object
    nlp: object
    solution: Solution
    history: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    sigma: float = 0.0
    sigma_source: str = ""
    budget: object = None
    """The ``budget.Budget`` of the fit; ``budget.stopped`` names the stages its limit cut."""


def noise_level(view, support=None) -> tuple[float, str, list]:
    """(sigma, source, notes): the capture's noise std checked against the data, or the data's.

    The data's estimate is the robust std (MAD) of the bins no modelled path reaches (``support``
    = flat indices of the modelled bins), else of the traces' first differences."""
    from ..view import noise_from_data

    stir = view.capture.stir
    notes = []
    # two robust estimates: first differences of every trace (returns occupy few bins), and the
    # bins no modelled path reaches (unmodelled returns can inflate it): the smaller is kept
    data = noise_from_data(stir.reshape(-1, stir.shape[-1]))
    off = np.zeros(0)
    if support is not None:
        mask = np.ones(stir.size, bool)
        mask[support] = False
        off = stir.reshape(-1)[mask]
        if off.size >= 200:
            med = np.median(off)
            d_off = float(np.median(np.abs(off - med)) / 0.6745)
            data = min(data, d_off) if data > 0 and d_off > 0 else max(data, d_off)
    if data == 0.0:  # quantised or noise-free data: a floor at the arithmetic's resolution
        peak = float(np.max(np.abs(stir))) or 1.0
        data = 1e-8 * peak
        notes.append(f"the data show no measurable noise (quantised or noise-free); sigma {data:.3g} "
                     "= 1e-8 of the peak")
        return data, "floor (noise-free data)", notes
    cap = view.capture_sigma
    if cap:
        if data > 1.5 * cap:
            notes.append(f"the capture's noise sigma {cap:.3g} is below the data's {data:.3g}; the "
                         "larger is used")
            return data, "data (the capture's sigma is too small)", notes
        return cap, "capture", notes
    return data, "estimated from the data", notes


def fit_model(model, stir, settings=None, noise: dict | None = None, sigma=None, warm=None,
              x0=None):
    """Solve one set-up model against a STIR and return its ``JointEstimate`` (twin experiments
    and user-built models; ``fit_joint`` is the full route with the hidden-patch search).
    ``warm``: a previous estimate (its solution restarts IPOPT)."""
    from .settings import EstimateSettings

    nlp = JointNLP(model, stir, settings or EstimateSettings(), sigma=sigma, noise=noise)
    w = warm.extra["solution"] if warm is not None else None
    sol = solve_lm(nlp, x0=x0) if nlp.settings.solver == "lm" else solve_nlp(nlp, x0=x0, warm=w)
    est = assemble(nlp, sol, model.names)
    est.extra["nlp"] = nlp
    return est


def _solve(nlp, warm=None, x0=None, strict: bool = True, first: bool = False):
    """Solve; when IPOPT cannot converge because the data leave directions flat (a degenerate
    problem: it crawls along the valley), hold the unknowns of those directions
    (``uncertainty.degenerate`` at the point reached) and solve again from there. The held
    unknowns are reported unidentified (``nlp.frozen``). Past the time limit nothing is built
    (a non-success ``Solution`` comes back), except for the ``first`` fit of an estimate, which
    IPOPT's ``max_wall_time`` (at least 1 s) bounds."""
    from .uncertainty import degenerate

    nlp.frozen = []
    if not first and _out_of_time(nlp):   # no solver is built past the limit (an exact Hessian's build alone
        # can take minutes on a 147-patch model)
        x = np.clip(np.asarray(x0 if x0 is not None else (warm.x if warm is not None else nlp.x0), float),
                    nlp.lbx, nlp.ubx)
        return Solution(x, False, WALL_TIME_STATUS, 0, float("nan"), 0.0, 0.0, solver="none")
    if nlp.settings.solver == "lm":
        return solve_lm(nlp)
    if len(nlp.y) * nlp.n_x > 2e8 and not nlp.poisson and not nlp.pem:
        # too large for IPOPT's exact Hessian: Levenberg-Marquardt on the sparse Jacobian
        from .lm import solve_sparse_lm
        return solve_sparse_lm(nlp, x0=x0 if x0 is not None else (warm.x if warm is not None else None))
    st = nlp.settings.ipopt
    raise_ = st.raise_on_failure
    with _raising(st, False):
        sol = solve_nlp(nlp, warm=warm, x0=x0)
        if sol.success or _out_of_time(nlp):
            return sol   # a solve the time limit stopped is returned as it is (not a success)
        rescued = _rescue(nlp, sol)
    if rescued is not None:
        return rescued
    if _out_of_time(nlp):   # the limit came during the Gauss-Newton continuation
        return sol
    frozen = degenerate(nlp, sol.x)
    if frozen:
        nlp.frozen = frozen
        nlp.lbx, nlp.ubx = nlp.lbx.copy(), nlp.ubx.copy()
        nlp.lbx[frozen] = nlp.ubx[frozen] = np.clip(sol.x[frozen], nlp.lbx[frozen], nlp.ubx[frozen])
        with _raising(st, False):
            sol = solve_nlp(nlp, x0=np.clip(sol.x, nlp.lbx, nlp.ubx))
    # a solve the time limit stopped is returned (the caller falls back), never raised
    if not sol.success and raise_ and strict and not _out_of_time(nlp):
        raise SolverError(f"IPOPT did not converge: return_status '{sol.status}' after "
                          f"{sol.iterations} iterations (cost {sol.cost:.6g}). Try a better initial "
                          "guess, more max_iter, or check that the data match the model.",
                          status=sol.status, stats={"iterations": sol.iterations})
    return sol


def _out_of_time(nlp) -> bool:
    b = getattr(nlp, "budget", None)
    return b is not None and b.expired()


@contextlib.contextmanager
def _raising(ipopt_settings, flag: bool):
    """Within the block, failed solves raise (``flag``) or return their Solution; restored after."""
    old = ipopt_settings.raise_on_failure
    ipopt_settings.raise_on_failure = flag
    try:
        yield
    finally:
        ipopt_settings.raise_on_failure = old


def _rescue(nlp, sol):
    """IPOPT stopped short (iteration limit, a failed step computation, restoration) on a
    weighted least-squares problem: continue from its last iterate with Gauss-Newton /
    Levenberg-Marquardt on the same cost and constraints (``lm.solve_sparse_lm``), which has no
    barrier to drive and no KKT system to factor. Its solution counts only when it converges and
    satisfies every constraint; otherwise None (the caller goes on as before). Called with
    failures not raising."""
    if nlp.poisson or nlp.pem:
        return None
    from .lm import solve_sparse_lm

    # a continuation, not a second solve: a point Gauss-Newton cannot finish in 30 steps is not
    # near a solution (and the caller's refusal comes sooner)
    alt = solve_sparse_lm(nlp, x0=np.clip(sol.x, nlp.lbx, nlp.ubx), max_iter=30)
    if alt.success and alt.cost <= sol.cost * (1 + 1e-9) + 1e-9:
        log.info(f"IPOPT stopped ({sol.status}, cost {sol.cost:.6g}); Gauss-Newton from its last "
                 f"iterate converged (cost {alt.cost:.6g}, {alt.iterations} iterations)")
        return alt
    return None


def _screen(nlp, max_iter: int = 25):
    """A screening fit for a likelihood-ratio test (does one more unknown lower chi2 by more than
    the threshold?): Gauss-Newton from the model's start, at most ``max_iter`` steps. A point it
    reaches that satisfies every constraint gives a chi2 no lower than the optimum's, so a drop
    past the threshold there is a drop past it at the optimum (the test stays valid, it only
    loses power); no IPOPT solve to the last digit. ``success`` means the point is feasible.
    Poisson and PEM costs go through IPOPT (``_solve``)."""
    if nlp.poisson or nlp.pem:
        return _solve(nlp, strict=False)
    from .lm import solve_sparse_lm

    with _raising(nlp.settings.ipopt, False):
        sol = solve_sparse_lm(nlp, max_iter=max_iter)
    sol.success = bool(sol.info.get("constraint_violation", np.inf) <= 1e-6)
    return sol


def _candidate_fit(nlp):
    """The refit of a hidden candidate with the known patches held: a few unknowns against every
    bin, so Gauss-Newton on the sparse Jacobian first (no exact Hessian of the whole STIR, no KKT
    system); IPOPT (``_solve``) from where it stopped when it does not converge in 30 steps.
    Poisson and PEM costs, and ``solver='lm'``, go to ``_solve`` directly."""
    if nlp.poisson or nlp.pem or nlp.settings.solver == "lm":
        return _solve(nlp)
    from .lm import solve_sparse_lm

    with _raising(nlp.settings.ipopt, False):
        sol = solve_sparse_lm(nlp, max_iter=30)
    if sol.success:
        return sol
    return _solve(nlp, x0=np.clip(sol.x, nlp.lbx, nlp.ubx))


def _glossy_patches(view, start, settings, make_nlp, stir, notes) -> np.ndarray:
    """Which visible patches the data show to be glossy: from an all-Lambertian fit, each patch in
    turn gets modified-Phong unknowns (specular, exponent) and keeps them when the whitened chi2
    drops by more than the likelihood-ratio threshold for two unknowns (``search.p_value``); the
    others stay Lambertian (a Phong lobe the data never see would make their albedo unidentifiable).
    Above 30 patches every patch is modelled glossy (the selection would cost one fit per patch)."""
    M = len(view.ids)
    if M > 30:
        return np.ones(M, bool)
    def chi2_of(mask):
        try:
            nk = make_nlp(plan_model(view, start, settings, [], brdf=mask, bounces=settings.bounces))
            sk = _solve(nk, strict=False)
        except SolverError:
            return None
        return _model_chi2(nk, sk.x, stir) if sk.success else None

    gl = np.zeros(M, bool)
    chi2_cur = chi2_of(gl)
    thr = lr_threshold(settings.search.p_value, 2)
    while chi2_cur is not None and not gl.all():  # forward selection: the largest drop first
        drops = {}
        for k in np.flatnonzero(~gl):
            mask = gl.copy()
            mask[k] = True
            c = chi2_of(mask)
            if c is not None:
                drops[k] = chi2_cur - c
        if not drops:
            break
        k = max(drops, key=drops.get)
        if drops[k] <= thr:
            break
        gl[k] = True
        chi2_cur -= drops[k]
    names = [f"V{int(i)}" for i in view.ids]
    notes.append("glossy (modified Phong) by the likelihood-ratio test: "
                 + (", ".join(names[k] for k in np.flatnonzero(gl)) or "none")
                 + f"; the others stay Lambertian (chi2 drop below {thr:.3g})")
    log.info(notes[-1])
    return gl


def _model_chi2(nlp, x, stir) -> float:
    """Whitened chi2 of ``nlp``'s model at x over every bin of the STIR."""
    r = nlp.whiten(stir, nlp.model.simulate(x[:nlp.model.n_x]))
    return float(np.sum(r * r))


def fit_joint(view, start: VisibleStart, settings, n_hidden: int | None = None,
              brdf: str = "lambertian", hidden_starts: list | None = None,
              budget: Budget | None = None) -> FitResult:
    """Fit the capture ``view`` from the visible ``start`` (see the module docstring).

    The hidden-patch search tests each candidate in a quick model (the known patches held at
    their fitted values, the candidate a point patch); the accepted ones then enter the final
    joint fit with everything free.

    ``budget`` (default: ``settings.time_limit`` from now): where it runs out, the stages not
    finished are skipped and the estimate is the last fit that converged with every unknown free,
    ``budget.stopped`` naming what was cut (see ``joint.budget``)."""
    from .policy import flatland_plane

    budget = budget if budget is not None else Budget(settings.time_limit)

    stir = view.capture.stir
    hidden: list[HiddenStart] = list(hidden_starts or [])
    t0 = time.perf_counter()
    noise = dict(view.capture.noise or {})
    if view.noise_model == "poisson" and settings.cost.likelihood == "gaussian":
        # photon counts: least squares weighted by the Poisson variance (counts per STIR unit)
        settings = copy.deepcopy(settings)
        settings.cost.weighting = "counts"
        noise["scale"] = float(noise.get("scale") or 1.0)
    plan = plan_model(view, start, settings, hidden, brdf=brdf, bounces=settings.bounces)
    sigma, s_src, notes = noise_level(view, plan.model.support)
    if view.noise_model == "poisson":
        sigma, s_src = 1.0 / noise["scale"], "Poisson counts (variance = mean)"
    notes = plan.notes + notes

    def make_nlp(pl):
        nlp_ = JointNLP(pl.model, stir, settings, sigma=(sigma, s_src), noise=noise, gauge=pl.gauge,
                        flat=pl.flat)
        nlp_.budget = budget
        return nlp_

    M = len(view.ids)
    if brdf == "phong" and not hidden:
        brdf = _glossy_patches(view, start, settings, make_nlp, stir, notes)
        plan = plan_model(view, start, settings, hidden, brdf=brdf, bounces=settings.bounces)
    nlp = make_nlp(plan)
    sol = _solve(nlp, strict=settings.bounces is not None, first=True)
    full = (plan, nlp, sol) if sol.success else None   # the last converged fit, all unknowns free
    # the bounce order the data call for: add one while its paths show above the noise
    K = plan.model.bounces
    k_max = settings.bounces or (4 if M <= 20 else 3)
    deg = max(float(np.asarray(plan.model.visibility).sum(axis=1).mean()), 1.0)
    while settings.bounces is None and K < k_max:
        if budget.expired():
            budget.stop("bounce-order probe")
            break
        if plan.model.info.n_paths * deg > 3e5:
            notes.append(f"bounce order held at {K}: the next order's ~{plan.model.info.n_paths * deg:.2g} "
                         "paths exceed the model's budget (its light, if above the noise, shows in chi2)")
            break
        # the next order's paths summed in NumPy at the fit (no CasADi graph unless it is kept)
        probe = plan_model(view, start, settings, hidden, brdf=brdf, bounces=K + 1, symbolic=False)
        if probe.model.n_x != plan.model.n_x:
            break
        xk = sol.x[:plan.model.n_x]
        extra = probe.model.simulate(xk) - plan.model.simulate(xk, numeric=True)
        big = float(np.max(np.abs(nlp.whiten(extra, 0.0 * extra))))
        log.info(f"bounce {K + 1}: its paths reach {big:.3g} noise std at the fit")
        if big <= 3.0:
            break
        K += 1
        plan_k = plan_model(view, start, settings, hidden, brdf=brdf, bounces=K)
        plan, nlp = plan_k, make_nlp(plan_k)
        sol = _solve(nlp, x0=np.clip(sol.x, nlp.lbx, nlp.ubx), strict=False)
        if sol.success:
            full = (plan, nlp, sol)
    want_search = settings.search.enabled and (n_hidden is None or n_hidden > len(hidden)) \
        and view.template is not None
    if not sol.success and not budget.expired():  # the bounce order is settled: the solve must
        # converge now, unless returns of hidden patches it cannot model may be what holds it
        # back (the search is next)
        sol = _solve(nlp, x0=np.clip(sol.x, nlp.lbx, nlp.ubx), strict=not want_search)
        if sol.success:
            full = (plan, nlp, sol)
        else:
            log.info(f"the visible-only fit did not converge ({sol.status}); searching its residual "
                     "for hidden patches (the final fit must converge)")
    chi2_cur = _model_chi2(nlp, sol.x, stir)
    history = [{"n_hidden": len(hidden), "chi2": chi2_cur, "status": sol.status,
                "wall_time_s": time.perf_counter() - t0}]
    log.info(f"fit of the visible patches: chi2/dof {chi2_cur / stir.size:.3g} over all bins "
             f"({sol.status}, {sol.iterations} iterations)")
    th = plan.model.theta(sol.x[:plan.model.n_x])
    vis_start = VisibleStart(th["position"][:M], start.position_std, th["normal"][:M],
                             th["albedo"][:M], th["area_value"][:M], start.pairs, th["gain"],
                             start.flat_labels)
    cur_nlp, cur_x = nlp, sol.x
    plane = flatland_plane(view, start.positions) if view.priors.get("flatland") else None
    max_h = settings.search.max_hidden if n_hidden is None else n_hidden
    tmpl = view.template
    tried: list = []   # every point proposed so far: a point whose patch the refit moved away
    # from (its return still unexplained there) is not proposed again
    while want_search and len(hidden) < max_h:
        if budget.expired():
            budget.stop("hidden-patch search")
            break
        R = cur_nlp.whiten(stir, cur_nlp.model.simulate(cur_x[:cur_nlp.model.n_x]))
        ex = [h.position for h in hidden] + tried
        cand = search(R, view, vis_start.positions, vis_start.normals,
                      np.clip(vis_start.albedo, 0.05, 1.0), tmpl,
                      step=settings.search.grid_step_irf * tmpl.width,
                      max_traces=settings.search.max_traces,
                      exclude=np.array(ex) if ex else None, plane=plane)
        if cand is None:
            break
        tried.append(np.asarray(cand.position, float))
        if n_hidden is None and not cand.significant():
            log.info(f"search: the strongest residual return (T = {cand.statistic:.3g} over "
                     f"{cand.n_tested} points) is what noise reaches: no further hidden patch")
            break
        hs = HiddenStart(cand.position, cand.normal, albedo_area=float(np.clip(cand.beta / 0.25, 1e-6, 0.5)))
        try:
            planq = plan_model(view, vis_start, settings, hidden + [hs], brdf=brdf, fixed_visible=True,
                               extended=False, bounces=K)
            nlpq = make_nlp(planq)
            solq = _candidate_fit(nlpq)
        except SolverError as exc:
            notes.append(f"a hidden candidate at {np.round(cand.position, 3).tolist()} could not be fitted "
                         f"({exc.status}); the search stopped there")
            break
        chi2_q = _model_chi2(nlpq, solq.x, stir)
        k_add = 3 + (2 if plane is None else 0)     # position, normal, albedo x area of one point
        thr = lr_threshold(settings.search.p_value, k_add)
        gain = chi2_cur - chi2_q
        log.info(f"hidden candidate {len(hidden) + 1} at {np.round(cand.position, 3).tolist()} "
                 f"(T = {cand.statistic:.3g}): chi2 drop {gain:.4g} vs threshold {thr:.3g}")
        if not solq.success or (n_hidden is None and gain <= thr):
            if not solq.success and budget.expired():
                budget.stop("hidden-patch search")
            break
        thq = planq.model.theta(solq.x[:planq.model.n_x])
        hidden = [HiddenStart(thq["position"][M + j], thq["normal"][M + j], float(thq["albedo"][M + j]),
                              4e-4, "search") for j in range(len(hidden) + 1)]
        cur_nlp, cur_x, chi2_cur = nlpq, solq.x, chi2_q
        history.append({"n_hidden": len(hidden), "chi2": chi2_q, "chi2_drop": gain, "threshold": thr,
                        "statistic": cand.statistic, "status": solq.status,
                        "wall_time_s": time.perf_counter() - t0})
    if n_hidden is not None and len(hidden) < n_hidden:
        notes.append(f"--hidden {n_hidden}: only {len(hidden)} hidden patches could be placed")
    extended = set()
    if hidden and settings.search.extended:  # which hidden patches show their size
        for j in range(len(hidden)):
            if budget.expired():
                budget.stop("extent screening")
                break
            try:
                pl_e = plan_model(view, vis_start, settings, hidden, brdf=brdf, fixed_visible=True,
                                  extended={j}, bounces=K)
                nlp_e = make_nlp(pl_e)
                sol_e = _screen(nlp_e)
            except SolverError:
                continue
            gain = chi2_cur - _model_chi2(nlp_e, sol_e.x, stir)
            if sol_e.success and gain > lr_threshold(settings.search.p_value, 1):
                extended.add(j)
        log.info(f"hidden patches whose extent the data resolve: {sorted(extended) or 'none'}")
    if hidden and not budget.expired():  # the final joint fit: everything free
        plan = plan_model(view, vis_start, settings, hidden, brdf=brdf, bounces=K, extended=extended)
        nlp = make_nlp(plan)
        sol = _solve(nlp)
        history.append({"n_hidden": len(hidden), "final": True,
                        "chi2": _model_chi2(nlp, sol.x, stir), "status": sol.status,
                        "wall_time_s": time.perf_counter() - t0})
        if not sol.success and budget.expired():
            budget.stop("final joint fit")
    elif hidden:
        budget.stop("final joint fit")
    if budget.stopped:
        where = ", ".join(budget.stopped)
        if full is None:
            raise SolverError(f"the time limit of {budget.limit:g} s ran out ({where}) before any fit "
                              f"converged ({budget.elapsed():.0f} s spent). Allow more time "
                              "(--time-limit SECONDS, 0 for none) or a smaller problem.",
                              status=WALL_TIME_STATUS, stats=budget.to_dict())
        lost = [np.round(h.position, 3).tolist() for h in hidden]
        plan, nlp, sol = full
        notes.append(budget.summary() + " (the visible patches' fit)"
                     + (f"; hidden candidates found but not refined: {lost}" if lost else ""))
        log.warning(notes[-1])
    if not sol.success:
        raise SolverError(f"the fit of the visible patches did not converge ({sol.status}) and no hidden "
                          "patch explains its residual. Check that the data match the model (bounces, "
                          "IRF, noise level) or give a better start.", status=sol.status,
                          stats=getattr(sol, "info", None))
    est = assemble(nlp, sol, plan.names, given=plan.given)
    est.extra["search_history"] = history
    return FitResult(est, plan, nlp, sol, history, notes, sigma, s_src, budget)


def lr_threshold(p: float, k: int) -> float:
    """chi-square quantile of 1 - p with k degrees of freedom (the search's acceptance level)."""
    return float(chi2_dist.ppf(1.0 - p, max(k, 1)))
