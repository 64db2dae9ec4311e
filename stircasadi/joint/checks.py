"""Self-checks of an estimate against the data — no truth needed (a result carries its verdict).

Each check returns ``Check(name, passed, value, limit, message)``; any failure makes the
estimate UNRELIABLE (``success`` false, non-zero exit). The checks:

* ``solver``: every solve converged.
* ``chi2``: the whitened residual chi2/dof of the final fit is below ``chi2_max`` (between its
  noise level and the limit the std were inflated by sqrt(chi2/dof), see ``uncertainty``).
* ``linearity``: the covariance describes the likelihood. Along the one-sigma direction of each
  unknown the data see (v_j = C e_j / sqrt(C_jj)), the whitened chi2 of the model itself must
  rise as its Gauss-Newton linearisation predicts, within a factor ``linearity_k``. Where it
  does not, the likelihood is curved at the scale of its own error bars (a banana-shaped valley:
  measured on nine patches on three planes, uncalibrated, chi2 rising 1000 where 1 was predicted
  while the albedos lay 4-6 of their std off), so the std cannot be trusted.
* ``flat-alternative`` (an uncalibrated frame only): the estimate must not lie within its own
  error bars of a flat configuration. Distances fix a point's height above the plane of the
  others only at second order near that plane (a height h moves every path by ~h^2 / 2r): with
  the visible patches, source and camera coplanar, the fitted heights come out of the noise and
  their Fisher std (the curvature at the estimate, which grows with the height itself) gives
  |height| / std = |err| / std whatever the noise (measured: ten patches on two walls in one
  plane with the source, heights 1-13 cm with std 2-26 mm, |err|/std 5.6, success true). The
  check fails when the heights above the best plane through the source (and camera) are all
  within ``alternative_k`` of their std from zero, on a configuration within 20 % of its span
  of flat.
* ``trace-residuals``: no trace's whitened chi2 exceeds the chi-square quantile of
  1 - trace_p / n_traces (a swapped or corrupted trace, a return the model misplaces).
* ``unexplained-returns``: the residual's matched filter (the impulse response) stays below
  ``unexplained_k`` noise std on every trace and bin, inside and outside the modelled windows.
* ``reciprocity``: with source and camera at one point the STIR is symmetric (Helmholtz), so
  traces (i, j) and (j, i) must agree within their noise: a model-free test of the data and of
  the id bookkeeping.
* ``hidden-placed``: every hidden patch the data asked for has an identified position.
* ``time-limit``: the estimate's time limit (``EstimateSettings.time_limit``) did not cut any
  stage short (present only when it did).
* ``plausibility``: every first-bounce path is positive and the scene fits in ``max_extent_m``;
  the impulse response is between 0.1 mm and 3 m of path (10 ns) wide (a bin width given in the
  wrong unit shows here).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_dist

__all__ = ["Check", "run_checks", "capture_checks"]

MAX_EXTENT_M = 1000.0
IRF_FWHM_RANGE_M = (1e-4, 3.0)


@dataclass
class Check:
    name: str
    passed: bool
    value: float
    limit: float
    message: str

    def to_dict(self) -> dict:
        return {"name": self.name, "passed": bool(self.passed), "value": float(self.value),
                "limit": float(self.limit), "message": self.message}


def capture_checks(view) -> list[Check]:
    """Checks on the capture alone (before any fit): the impulse response's width."""
    out = []
    fw = float(getattr(view.irf, "fwhm", 0.0) or 0.0)
    if fw > 0:
        lo, hi = IRF_FWHM_RANGE_M
        ok = lo <= fw <= hi
        out.append(Check("plausibility", ok, fw, hi,
                         f"impulse response FWHM {fw:.4g} m of path ({fw / 299792458.0 * 1e12:.4g} ps)"
                         + ("" if ok else f" is outside [{lo:g}, {hi:g}] m: is the bin width "
                            f"({view.grid.bin_width:g} m) in the right unit?")))
    return out


def _reciprocity(view, nlp, k_lim, p, model_stir) -> Check | None:
    """Traces (i, j) and (j, i) compared on the bins where the fitted model predicts light (the
    bins are chosen without looking at the data's noise, so the test is unbiased)."""
    if not view.colocated or view.capture.stir is None:
        return None
    stir = view.capture.stir
    ill, obs = list(view.ill), list(view.obs)
    both = [i for i in ill if i in obs]
    stats = []
    for a in range(len(both)):
        for b in range(a + 1, len(both)):
            i, j = both[a], both[b]
            yij = stir[ill.index(i), obs.index(j)]
            yji = stir[ill.index(j), obs.index(i)]
            mij = model_stir[ill.index(i), obs.index(j)]
            mji = model_stir[ill.index(j), obs.index(i)]
            sd = np.broadcast_to(nlp.bin_std(0.5 * (mij + mji)), mij.shape)
            sel = (np.abs(mij) > sd) | (np.abs(mji) > sd)
            if sel.sum() < 3:
                continue
            d = (yij[sel] - yji[sel]) / (np.sqrt(2.0) * sd[sel])
            stats.append((float(d @ d), int(sel.sum()), (int(i), int(j))))
    if not stats:
        return None
    n = len(stats)
    pv = [chi2_dist.sf(s, k) for s, k, _ in stats]
    k_min = int(np.argmin(pv))
    ok = pv[k_min] >= p / n
    s, k, pair = stats[k_min]
    return Check("reciprocity", ok, s / k, float(chi2_dist.ppf(1 - p / n, k) / k),
                 f"traces {pair} and their reciprocal differ by chi2/n = {s / k:.3g} over {k} bins"
                 + ("" if ok else " — the STIR is not symmetric although source and camera coincide: "
                    "traces are swapped or mislabelled, or the noise level is wrong"))


def run_checks(view, fit, settings, first_paths=None) -> list[Check]:
    """Every check on a finished joint fit ``fit`` (``joint.fit.FitResult``); ``first_paths``: the
    first-bounce path lengths the onsets measured (they must be positive)."""
    cs, us = settings.checks, settings.uncertainty
    nlp, sol, est = fit.nlp, fit.solution, fit.estimate
    model = nlp.model
    out = capture_checks(view)
    out.append(Check("solver", bool(sol.success), float(sol.iterations), float(nlp.settings.ipopt.max_iter),
                     f"{sol.solver} status '{sol.status}' after {sol.iterations} iterations"))
    red = est.chi2_dof
    out.append(Check("chi2", red <= us.chi2_max, red, us.chi2_max,
                     f"whitened residual chi2/dof = {red:.4g} over {est.dof} degrees of freedom "
                     f"(noise sigma {nlp.sigma:.3g}, {nlp.sigma_source})"
                     + ("" if red <= us.chi2_max else ": the model does not explain the data")))
    budget = getattr(fit, "budget", None)
    cut = budget is not None and bool(budget.stopped)
    if cut:
        out.append(Check("time-limit", False, budget.elapsed(), budget.limit,
                         budget.summary() + ", not the full estimate (allow more time: --time-limit "
                         "SECONDS, 0 for none)"))
    # the linearity probe is skipped for a result the limit already marks incomplete
    lin = None if cut else _linearity(nlp, sol.x, est.extra.get("cov_x"), est.extra.get("null_x"),
                                      cs.linearity_k, cs.linearity_max_dirs)
    if lin is not None:
        out.append(lin)
    flat = None if cut else _flat_alternative(view, nlp, sol.x, est.extra.get("cov_x"), cs.alternative_k,
                                              est.identifiable.get("position"))
    if flat is not None:
        out.append(flat)
    # per-trace whitened chi2 on the modelled bins
    r = nlp.whitened_residuals(sol.x)
    tr = model.support_trace
    n_tr = int(tr.max()) + 1 if len(tr) else 0
    c2 = np.bincount(tr, r * r, minlength=n_tr)
    nb = np.bincount(tr, minlength=n_tr)
    has = nb > 0
    if has.any():
        p_tr = chi2_dist.sf(c2[has], nb[has])
        n_has = int(has.sum())
        worst = int(np.argmin(p_tr))
        t_idx = np.flatnonzero(has)[worst]
        ri, ci = divmod(int(t_idx), len(view.obs))
        ok = p_tr[worst] >= cs.trace_p / n_has
        n_bad = int(np.sum(p_tr < cs.trace_p / n_has))
        out.append(Check("trace-residuals", ok, float(c2[t_idx] / nb[t_idx]),
                         float(chi2_dist.ppf(1 - cs.trace_p / n_has, nb[t_idx]) / nb[t_idx]),
                         f"worst trace (pulse at {int(view.ill[ri])}, seen from {int(view.obs[ci])}): "
                         f"chi2/n = {c2[t_idx] / nb[t_idx]:.3g} over {int(nb[t_idx])} bins"
                         + ("" if ok else f"; {n_bad} traces are not explained by the model")))
    # returns left in the residual anywhere (the matched filter of the impulse response)
    tmpl = view.template
    stir = view.capture.stir
    pred = model.simulate(sol.x[:model.n_x])
    if tmpl is not None:
        from .search import matched_filters

        R = nlp.whiten(stir, pred)
        mf, e, _ = matched_filters(R.reshape(-1, stir.shape[-1]), tmpl, view.grid)
        z = mf / np.sqrt(e)
        zmax = float(z.max()) if z.size else 0.0
        t_idx, k = np.unravel_index(int(np.argmax(z)), z.shape) if z.size else (0, 0)
        ri, ci = divmod(int(t_idx), len(view.obs))
        n_sig = int(np.sum(np.any(z > cs.unexplained_k, axis=1)))
        ok = zmax <= cs.unexplained_k
        out.append(Check("unexplained-returns", ok, zmax, cs.unexplained_k,
                         f"largest residual return {zmax:.3g} noise std (pulse at {int(view.ill[ri])}, "
                         f"seen from {int(view.obs[ci])}, path {view.grid.centres[k]:.4g} m)"
                         + ("" if ok else f"; {n_sig} traces hold returns no modelled patch explains")))
    # hidden patches the data ask for must be placed: a return explained by a patch whose
    # position the data cannot pin (two visible patches: a circle; collinear ones: a ring) is
    # not a placed patch
    M_vis = len(view.ids)
    n_h = len(est.identifiable["position"]) - M_vis
    if n_h > 0:
        bad = [k - M_vis + 1 for k in range(M_vis, M_vis + n_h) if not est.identifiable["position"][k]]
        out.append(Check("hidden-placed", not bad, float(len(bad)), 0.0,
                         f"{n_h - len(bad)} of {n_h} hidden patches placed"
                         + ("" if not bad else f"; the returns of hidden patches {bad} are explained but "
                            "their positions are not identified (the visible patches do not pin them: "
                            "two of them leave a circle, collinear ones a ring) — give a prior "
                            "(--flatland) or more visible patches")))
    rc = _reciprocity(view, nlp, cs.reciprocity_k, cs.trace_p, pred)
    if rc is not None:
        out.append(rc)
    # plausibility of the geometry
    z_ = est.values["position"]
    leg = np.linalg.norm(z_ - view.source, axis=1)
    ext = float(np.max(np.linalg.norm(z_ - z_.mean(axis=0), axis=1))) if len(z_) else 0.0
    first = np.asarray(first_paths, float) if first_paths is not None else leg
    first = first[np.isfinite(first)]
    ok = bool(np.all(np.isfinite(leg)) and ext <= MAX_EXTENT_M and np.all(first > 0))
    out.append(Check("plausibility", ok, ext, MAX_EXTENT_M,
                     f"scene extent {ext:.4g} m, source legs {leg.min():.4g}-{leg.max():.4g} m"
                     + (f", shortest first-bounce path {first.min():.4g} m" if len(first) else "")
                     + ("" if ok else ": implausible geometry (is the time axis' start or unit right?)")))
    return out


def _flat_alternative(view, nlp, x, cov_x, k: float, reported=None) -> Check | None:
    """The ``flat-alternative`` check (module docstring); None where it does not apply (a frame
    the capture fixes, fewer than three free visible positions reported (``reported``: the
    estimate's identifiable flags; a position reported null claims nothing), no covariance, the
    camera off the plane, a configuration far from flat: heights above 20 % of its span)."""
    if view.frame != "source-origin" or cov_x is None:
        return None
    model = nlp.model
    M = len(view.ids)
    try:
        free = np.asarray(model.params["position"].free, bool)
        free = (free.reshape(len(free), -1).any(axis=1))[:M]
        Pj = np.asarray(model.params.position_jacobian(), float)[:M]      # (M, 3, n_params)
    except (KeyError, AttributeError, ValueError):
        return None
    if reported is not None:
        free = free & np.asarray(reported, bool)[:M]
    if int(free.sum()) < 3:
        return None
    x = np.asarray(x, float)
    P = np.asarray(model.theta(x[:model.n_x])["position"], float)[:M]
    anchor = np.asarray(view.source, float)
    fixed = [np.zeros(3)] + ([] if view.colocated else [np.asarray(view.camera, float) - anchor])
    Q = np.vstack([P - anchor] + fixed)
    n = np.linalg.svd(Q, full_matrices=False)[2][-1]       # the best plane through the source
    span = float(np.max(np.linalg.norm(Q[:, None] - Q[None], axis=2)))
    if len(fixed) > 1 and abs(float(fixed[1] @ n)) > 1e-3 * span:
        return None                                          # the camera is off that plane
    h = ((P - anchor) @ n)[free]
    if float(np.max(np.abs(h))) > 0.2 * span:
        return None
    C = np.asarray(cov_x, float)
    npar = min(Pj.shape[2], C.shape[0])
    G = np.einsum("j,kjx->kx", n, Pj[free][:, :, :npar])   # d height / d x
    var = np.einsum("kx,xy,ky->k", G, C[:npar, :npar], G)
    sd = np.sqrt(np.clip(var, 0.0, None))
    with np.errstate(divide="ignore", invalid="ignore"):
        zh = np.where(sd > 0, np.abs(h) / sd, np.inf)
    worst = float(np.max(zh)) if zh.size else np.inf
    ok = not (worst < k)
    msg = (f"the visible patches lie within {np.max(np.abs(h)):.3g} m of one plane through the "
           f"source; their heights above it are at most {worst:.3g} of their std from zero")
    if not ok:
        msg += (f" (below {k:g}): the estimate is within its error bars of the flat configuration, "
                "where the distances fix the heights only at second order (a height h moves the "
                "paths by ~h^2 / 2r), so the heights, the positions they tilt and their std cannot "
                "be trusted. A calibrated camera, known points off that plane or patches away from "
                "it fix them")
    return Check("flat-alternative", ok, worst, float(k), msg)


def _linearity(nlp, x, cov_x, null_x, k_lim, max_dirs) -> Check | None:
    """The ``linearity`` check (module docstring): actual against linearised chi2 rise along the
    one-sigma direction of each unknown the data see (at most ``max_dirs``, evenly spread), both
    signs, steps that stay within the bounds. The directions the data do not see (``null_x``,
    where the weak prior fills the covariance and the numbers are reported not identifiable) are
    projected out of each step: the data say nothing there, linear or not. Gaussian likelihood
    only (None otherwise)."""
    from .uncertainty import prior_std_x

    if cov_x is None or getattr(nlp, "f_r", None) is None:
        return None
    x = np.asarray(x, float)
    n = min(len(x), cov_x.shape[0])
    C = np.asarray(cov_x, float)[:n, :n]
    prior = prior_std_x(nlp)[:n]
    d = np.diag(C)
    seen = np.flatnonzero(np.isfinite(d) & (d > 0) & (d < 0.25 * prior ** 2))
    if not len(seen):
        return None
    if len(seen) > max_dirs:
        seen = seen[np.linspace(0, len(seen) - 1, max_dirs).round().astype(int)]
    Qn = None
    if null_x is not None and np.asarray(null_x).size:
        Qn, _ = np.linalg.qr(np.asarray(null_x, float)[:n])
    r0 = nlp.residuals(x)
    c0 = float(r0 @ r0)
    J = nlp.jacobian_sparse(x)
    worst, where, n_dir = 1.0, None, 0
    for j in seen:
        v = np.zeros(len(x))
        v[:n] = C[:, j] / np.sqrt(d[j])
        if Qn is not None:
            v[:n] -= Qn @ (Qn.T @ v[:n])
        Jv = J @ v
        for sgn in (1.0, -1.0):
            xt = x + sgn * v
            if np.any(xt < nlp.lbx) or np.any(xt > nlp.ubx):
                continue
            lin = r0 + sgn * Jv
            pred = float(lin @ lin) - c0
            if pred < 0.25:          # the data alone barely see this direction: nothing to compare
                continue
            rt = nlp.residuals(xt)
            act = float(rt @ rt) - c0
            n_dir += 1
            ratio = max(act, 1e-12) / pred
            if abs(np.log(ratio)) > abs(np.log(worst)):
                worst, where = ratio, (nlp.x_names[j], sgn, act, pred)
    if n_dir == 0:
        return None
    ok = 1.0 / k_lim <= worst <= k_lim
    msg = (f"chi2 along the one-sigma directions of {len(seen)} unknowns rises as the linearised model "
           f"predicts within a factor {worst:.3g}" if where is None else
           f"chi2 along the one-sigma direction of {where[0]} ({'+' if where[1] > 0 else '-'}) rose by "
           f"{where[2]:.4g} where the linearised model predicts {where[3]:.4g} (factor {worst:.3g})")
    if not ok:
        msg += ("; the likelihood is curved at the scale of its own error bars, so the covariance "
                "does not describe it and the stds cannot be trusted (more signal, a declared prior "
                "or known geometry make it linear)")
    return Check("linearity", ok, float(worst), float(k_lim), msg)


#: visible patches whose rms distance from their best-fit line is below this fraction of the
#: line's extent count as collinear: the third-bounce path lengths of a hidden patch through
#: them are the same all round a ring about that line
COLLINEAR_REL = 0.01


def _collinear(Z) -> tuple[bool, str]:
    """Do the visible positions ``Z`` (M, 3) lie on one line (or one point)? (flag, description)."""
    Z = np.asarray(Z, float)
    Z = Z[np.isfinite(Z).all(axis=1)]
    if len(Z) <= 2:
        return True, f"{len(Z)} visible patch{'es' if len(Z) != 1 else ''}"
    c = Z.mean(axis=0)
    sv = np.linalg.svd(Z - c, compute_uv=False)
    extent = float(np.ptp((Z - c) @ np.linalg.svd(Z - c)[2][0]))
    perp = float(np.sqrt(np.sum(sv[1:] ** 2) / len(Z)))
    return perp <= COLLINEAR_REL * max(extent, 1e-12), (f"{len(Z)} visible patches on one line "
                                                          f"(rms {perp * 1e3:.3g} mm off it over "
                                                          f"{extent:.3g} m)")


def identifiability_check(view, ambiguities, visible_positions=None, n_hidden: int = 0) -> Check:
    """The onsets must fix the geometry the fit reports (``ambiguities`` from the geometry stage).

    Where the first-, second- and third-bounce onsets leave the positions a family -- visible
    patches of an uncalibrated scene with patch-to-patch distances missing
    (``underdetermined-embedding``), a hidden patch seen through two visible patches whose
    distances put it on a circle (``underdetermined``) -- only the amplitudes (albedos, areas,
    cosines: unknowns themselves) could pick a member, and their Fisher information is local: it
    cannot see the rest of the family, so the reported std would not cover the error (measured: a
    member 0.79 m from the truth with a 0.5 mm std; and, with five collinear relay-wall patches, a
    hidden patch placed on the right ring 0.79 m from the truth with a 1 mm std, coverage study
    seed 104). Hidden patches seen only through visible patches on one line (or one or two
    points) lie on a ring about that line: flagged from the positions themselves. A declared prior that removes the family
    (``flatland``: the circle meets the plane in two mirror points, which the fit tells apart) or
    a calibrated frame (visible positions given) lifts the check."""
    fam = []
    flat = view.priors.get("flatland", False)
    for a in ambiguities or []:
        kind = a.get("kind")
        if kind == "underdetermined-embedding" and view.frame != "capture":
            fam.append(("visible", a))
        elif kind == "underdetermined" and not flat:
            fam.append(("hidden", a))
    if n_hidden > 0 and visible_positions is not None and not flat and not any(k == "hidden" for k, _ in fam):
        col, what = _collinear(visible_positions)
        if col:  # every third-bounce path length is the same all round a ring about that line
            fam.append(("hidden", {"message": f"{what}: every hidden patch's path lengths are the same "
                                              "all round a ring about that line, so its position is a ring"}))
    msg = ("the onsets fix every reported position" if not fam else
           "the onsets leave the geometry a family, so the positions the fit reports are one member "
           "picked by the amplitudes alone: " + "; ".join(a["message"].rstrip(". ") for _, a in fam)
           + ". Declare what fixes it (--flatland, known wall points, a calibrated camera) or add "
             "patches whose second bounces measure the missing distances.")
    return Check("identifiability", not fam, float(len(fam)), 0.0, msg)

