"""Bounded Levenberg-Marquardt on a level's surface NLP (the default solver of ``fit_surface``).

The NLP (``SurfaceModel`` unknowns theta = (z, rho, sigma[, tail], b)):

    min  F(theta) = 1/2 sum_pk wgt_pk (m_pk(theta) - y_pk)^2 + 1/2 lam || Lap z / h ||^2
    s.t. 0 <= rho <= rho_max,  sigma and tail within their bounds.

Each iteration builds the exact Gauss-Newton matrix H = J^T W J and gradient g
(``SurfaceModel.linearise``), freezes the bounded unknowns whose gradient pushes them outward
(projected Newton; the depth of a node whose albedo and whose neighbours' albedos are near zero
is held: the data do not see it), solves (H + lam R + mu diag(H)) d = -g by Cholesky, limits the depth step
to ``slack``, projects onto the bounds and accepts the step when F decreases (mu / 3), else
retries with mu x 4. It needs 5-20 iterations where IPOPT's limited-memory Hessian needs
hundreds on the same problems (the GN matrix is dense: nodes couple through every trace that
sees them at similar delays).
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from scipy.stats import chi2 as _chi2_dist

from .model import SurfaceModel, SurfaceState

__all__ = ["solve_lm", "Bounds", "first_linearisation", "last_decrease", "nested_lr", "prior_penalty", "remaining_step",
           "CONVERGED_STD"]

#: the largest shrink of a cut cell's emitting part per side (``SurfaceModel(cell_extent=True)``)
SHRINK_MAX = 0.9
#: the largest shear |k| of a cut cell's emitting part (``SurfaceModel(cell_shear=True)``): a
#: right triangle of the cell's legs needs 0.41
SHEAR_MAX = 0.9


class Bounds:
    """Lower / upper bounds of ``SurfaceModel.pack``'s vector (depths free)."""

    def __init__(self, model: SurfaceModel, rho_max: float, sigma: tuple, tail: tuple,
                 beta: tuple = (0.0, 0.95), bgtau: tuple = (0.01, 5.0)):
        N = model.N
        lo = np.full(model.npar, -np.inf)
        hi = np.full(model.npar, np.inf)
        lo[N:2 * N], hi[N:2 * N] = 0.0, rho_max
        for i, name in enumerate(model.glob):
            if name == "sigma":
                lo[2 * N + i], hi[2 * N + i] = sigma
            elif name == "tail":
                lo[2 * N + i], hi[2 * N + i] = tail
            elif name.startswith("beta"):
                lo[2 * N + i], hi[2 * N + i] = beta
            elif name == "bgtau":
                lo[2 * N + i], hi[2 * N + i] = bgtau
        if model.K:     # the cells' centroid offsets stay inside their cells (any shrinks in [0, SHRINK_MAX])
            g1 = 2 * N + len(model.glob)
            hx, hy = 0.5 * model.grid.hx, 0.5 * model.grid.hy
            lo[g1:] = np.tile([-hx, -hy, 0.0, 0.0, -SHEAR_MAX][:model.E], model.K)
            hi[g1:] = np.tile([hx, hy, SHRINK_MAX, SHRINK_MAX, SHEAR_MAX][:model.E], model.K)
        self.lo, self.hi = lo, hi
        self.beta_idx = np.array([2 * N + i for i, k in enumerate(model.glob) if k.startswith("beta")], int)

    def project(self, th):
        out = np.clip(th, self.lo, self.hi)
        b = self.beta_idx
        if len(b) and out[b].sum() > 0.97:          # the slow tails' weights sum below 1
            out[b] *= 0.97 / out[b].sum()
        return out

    def at_bound(self, th):
        """Names of the globals at a bound (a fitted value the data push past its range)."""
        return np.isclose(th, self.lo, rtol=1e-6, atol=0) | np.isclose(th, self.hi, rtol=1e-6, atol=0)


def _solve(A, b):
    try:
        return -sla.cho_solve(sla.cho_factor(A, check_finite=False), b, check_finite=False)
    except (np.linalg.LinAlgError, ValueError):
        return -np.linalg.lstsq(A, b, rcond=None)[0]


def _damping(h, N, held=None):
    """Marquardt's diag(H), floored per block (depths, albedos, globals) at 1e-4 of the block's
    median so that unknowns the data hardly see (depths under a zero albedo) stay damped
    (``held``: the albedos held at zero, not linearised, left out of their block's median)."""
    d = np.array(h, float)
    for sl in (slice(0, N), slice(N, 2 * N)):
        blk = d[sl]
        ref = blk[~held] if (held is not None and sl.start == N and (~held).any()) else blk
        if blk.size:
            d[sl] = np.maximum(blk, 1e-4 * max(float(np.median(ref)), 1e-300))
    return np.maximum(d, 1e-12 * max(float(np.max(d)), 1e-300))


def _free(model, st, th, H, g, bounds, dH=None, need_step: bool = True):
    """The unknowns a Gauss-Newton step moves, and that undamped step on them. Projected
    Newton: unknowns at a bound whose gradient pushes outward stay there; the depth of a node
    the data do not see (albedo below 2 % of the largest, and its four neighbours' too: their
    normals depend on it) is not moved; and unknowns at a bound that the undamped step would push
    outward are held too (one pass of an active-set refinement: a step the bound cuts off makes
    no progress; an offset or an albedo at its bound otherwise stalls the solve with tiny
    projected steps). ``dH``: the damping's diagonal, 1e-10 of it regularises the step;
    without ``need_step`` the step on the final set is not formed (None)."""
    N = model.N
    free = ~(((th <= bounds.lo) & (g > 0)) | ((th >= bounds.hi) & (g < 0)) | (bounds.lo >= bounds.hi))
    free[:N] &= model.seen(st.rho)
    fi = np.flatnonzero(free)
    if not len(fi):
        return fi, np.zeros(0)
    reg = 1e-10 * (np.diag(H)[fi] if dH is None else dH[fi])
    d0 = _solve(H[np.ix_(fi, fi)] + np.diag(reg), g[fi])
    out = ((th[fi] <= bounds.lo[fi]) & (d0 < 0)) | ((th[fi] >= bounds.hi[fi]) & (d0 > 0))
    if not out.any():
        return fi, d0
    fi = fi[~out]
    return fi, (_solve(H[np.ix_(fi, fi)] + np.diag(reg[~out]), g[fi]) if need_step else None)


def last_decrease(solve: dict) -> float | None:
    """2 (F before - F after) of a solve's last accepted step (``history``): the whitened chi^2
    plus the prior's penalty it removed (far above 1: the solve had not converged), or None."""
    h = solve.get("history") or []
    return 2.0 * (h[-1]["f"] - h[-1]["f_new"]) if h else None


def nested_lr(f_restricted: float, f_general: float, chi2_general: float, dof_general: int, df: int,
              p: float) -> tuple[float, float]:
    """The likelihood ratio of two nested solves and its threshold: 2 (F_restricted - F_general)
    (F: a solve's chi^2 / 2 plus prior) divided by the general model's inflation
    max(1, chi2 / dof), against the chi^2 quantile of ``df`` (the unknowns the restriction
    removes) at ``p``. Returns (lr, threshold): the general model is needed where lr > threshold."""
    lr = 2.0 * (float(f_restricted) - float(f_general)) / max(1.0, float(chi2_general) / max(int(dof_general), 1))
    return lr, float(_chi2_dist.isf(p, max(int(df), 1)))


def prior_vector(st: SurfaceState, M: int) -> np.ndarray:
    """The unknowns a smoothness prior of size ``M`` acts on: the depths (M = N) or the depths
    and then the albedos (M = 2 N)."""
    return st.z if M == len(st.z) else np.concatenate([st.z, st.rho])


def held_albedos(bounds: Bounds, N: int) -> np.ndarray | None:
    """The albedos held at zero (``Bounds`` hi = 0: pruned nodes) as ``linearise``'s ``skip``
    (their pairs are not linearised), None where none is."""
    held = bounds.hi[N:2 * N] <= 0.0
    return held if held.any() else None


def first_linearisation(model: SurfaceModel, bounds: Bounds, st: SurfaceState, y, wgt, dtype):
    """``st`` projected to ``bounds`` and the linearisation there that ``solve_lm`` makes first
    (to hand it over as ``lin0`` after using it)."""
    st = model.unpack(bounds.project(model.pack(st)), st)
    return st, model.linearise(st, y, wgt, dtype=dtype, skip=held_albedos(bounds, model.N))


def prior_penalty(st: SurfaceState, lam: float, R_prior) -> float:
    """The prior's share of F, lam / 2 v^T R v (``prior_vector``; 0 without a prior)."""
    if not lam > 0:
        return 0.0
    v = prior_vector(st, R_prior.shape[0])
    return 0.5 * lam * float(v @ (R_prior @ v))


def prior_gradient(g: np.ndarray, st: SurfaceState, lam: float, R_prior) -> np.ndarray:
    """A copy of the data's gradient ``g`` (of chi^2 / 2) with the prior's, lam R v, added on the
    unknowns it acts on (``prior_vector``)."""
    g = np.array(g, float)
    if lam > 0:
        M = R_prior.shape[0]
        g[:M] += lam * (R_prior @ prior_vector(st, M))
    return g


def solve_lm(model: SurfaceModel, y, wgt, st: SurfaceState, lam: float, R_prior, bounds: Bounds,
             slack: float, max_iter: int = 30, tol: float = 1e-6, dtype=np.float32, lin0: dict | None = None,
             tol_chi2: float = 0.0, f_stop: float | None = None) -> dict:
    """Run LM from ``st`` on chi2 / 2 + lam / 2 v^T R_prior v, v the first M = R_prior.shape[0]
    unknowns (the depths, or the depths then the albedos: ``prior_vector``). Returns dict(state,
    status, iterations, success, f, at_bound,
    history): ``history`` holds one dict per accepted step, F before and after it (``f``,
    ``f_new``), the decrease the quadratic model predicted for the step taken (``predicted``:
    it matches f - f_new where the model is locally quadratic; a solve stopped by ``max_iter``
    whose last steps still lower F by far more than 1 has not converged), the damping ``mu``
    and the largest depth change ``dz_max`` (m). ``lin0``: ``model.linearise``'s result at ``st``,
    used for the first step instead of a new one (its H is modified in place).

    Stops ("Converged") when a step lowers F by less than ``tol`` relative (with ``tol_chi2`` > 0
    only once the undamped step confirms it, as below), or (``tol_chi2`` > 0) when a step's decrease of 2F and the decrease its quadratic model predicted are both below
    tol_chi2 max(1, chi2/dof): twice the predicted decrease of a Gauss-Newton step d is at least
    d^T H d, its squared length in the Fisher metric, so such a step moved the unknowns by less
    than tol_chi2^(1/2) of their (inflated) standard deviation, jointly; and the undamped
    Gauss-Newton step from the new point predicts less than the same (its g^T H^-1 g, in
    ``history[-1]["newton"]``), checked on the next linearisation: a damped step is short
    wherever the damping is large, whatever the distance left (on a seeded twin, a tilted square
    behind a paired relay at 0.3 % noise, LM stopped on damped steps with errors of 3-5 std
    left).

    ``f_stop``: the solve also stops ("Target reached", not a success) once a step brings F to
    ``f_stop`` or below (for a caller whose decision needs only F that low: F only falls further)."""
    N = model.N
    prior = lam > 0
    M = R_prior.shape[0]   # the prior acts on the depths (M = N) or on depths and albedos (2 N)

    def pen(s):
        return prior_penalty(s, lam, R_prior)

    th = bounds.project(model.pack(st))
    st = model.unpack(th, st)
    skip = held_albedos(bounds, N)      # albedos held at zero: their pairs are not linearised
    mu = 1e-3
    status, it, f = "Maximum_Iterations_Exceeded", 0, None
    dof = max(int(np.size(y)) - model.npar, 1)
    hist = []
    confirm = False
    for it in range(1, max_iter + 1):
        # (``lin0``: the caller's linearisation at the starting state, reused by the first step)
        lin = lin0 if (it == 1 and lin0 is not None) else model.linearise(st, y, wgt, dtype=dtype, skip=skip)
        f = 0.5 * lin["chi2"] + pen(st)
        H, g = lin["H"], prior_gradient(lin["g"], st, lam, R_prior)
        if prior:
            H[:M, :M] += lam * R_prior
        dH = _damping(np.diag(H), N, skip)
        fi, _ = _free(model, st, th, H, g, bounds, dH, need_step=False)
        Hf, gf, dHf = H[np.ix_(fi, fi)], g[fi], dH[fi]
        if confirm:
            # the last step was small, but a damped step is small wherever mu is large: stop
            # only when the undamped Gauss-Newton step from here predicts no more either (its
            # decrease of 2F, g^T H^-1 g, is the squared distance to the quadratic model's
            # minimum in the Fisher metric)
            confirm = False
            newton = -float(gf @ _solve(Hf + 1e-10 * np.diag(dHf), gf))
            hist[-1]["newton"] = newton
            if newton < tol_chi2 * max(1.0, lin["chi2"] / dof):
                status = "Converged (step below its std)"
                break
        accepted = False
        for _ in range(14):
            d = np.zeros_like(th)
            d[fi] = _solve(Hf + mu * np.diag(dHf), gf)
            big = float(np.max(np.abs(d[:N]))) if N else 0.0
            d[:N] = np.clip(d[:N], -slack, slack)     # nodes the data hardly see may not jump
            tn = bounds.project(th + d)
            sn = model.unpack(tn, st)
            chi2n, _ = model.objective(sn, y, wgt)
            fn = 0.5 * chi2n + pen(sn)
            if np.isfinite(fn) and fn < f:
                accepted = True
                dd = tn - th      # the step taken (clipped and projected)
                hist.append({"f": float(f), "f_new": float(fn),
                             "predicted": -float(g @ dd + 0.5 * dd @ (H @ dd)),
                             "mu": float(mu), "dz_max": float(np.max(np.abs(dd[:N]))) if N else 0.0}
                            | ({"do_max": float(np.max(np.abs(dd[-model.E * model.K:].reshape(model.K, -1)[:, :2])))} if model.K else {}))
                rel = (f - fn) / max(abs(f), 1e-300)
                small = False
                if tol_chi2 > 0:
                    infl = max(1.0, chi2n / dof)
                    small = max(2.0 * (f - fn), 2.0 * hist[-1]["predicted"]) < tol_chi2 * infl
                th, st, f = tn, sn, fn
                mu = max(mu / 3.0, 1e-9)
                break
            mu *= 4.0
        if not accepted:
            status = "Converged (no decrease possible)"
            break
        if rel < tol and tol_chi2 <= 0:
            status = "Converged"
            break
        if f_stop is not None and f <= f_stop:
            status = "Target reached"
            break
        if small or rel < tol:
            # checked on the next linearisation (above): a relative decrease below ``tol`` is
            # a short step too, and a damped step is short wherever mu is large
            confirm = True
    return {"state": st, "status": status, "iterations": it, "history": hist, "success": status.startswith("Converged"),
            "f": float(f), "at_bound": [n for i, n in enumerate(model.glob)
                                        if bounds.at_bound(th)[2 * N + i]]}


def remaining_step(model, state, A, g, mask, z_std, rho_std, bounds) -> dict:
    """The undamped Gauss-Newton step from the final state on the unknowns LM would move
    (``_free``: ``A`` the Gauss-Newton matrix with the prior, ``g`` the gradient with it), in
    units of the std: its largest change of a mask node's depth or albedo, and of any node's."""
    N = model.N
    th = model.pack(state)
    fi, step = _free(model, state, th, A, g, bounds)
    d = np.zeros(th.size)
    d[fi] = step
    rz = np.abs(d[:N]) / np.maximum(z_std, 1e-300)
    rr = np.abs(d[N:2 * N]) / np.maximum(rho_std, 1e-300)
    both = np.maximum(rz, rr)
    return {"max_std_mask": float(both[mask].max()) if mask.any() else None,
            "max_std_any": float(both.max()), "decrease_2F": float(-g[fi] @ step)}


#: the largest change of a mask node's depth or albedo, in std, that the remaining Gauss-Newton
#: step of a last level cut by its iteration limit may make for the fit to be judged converged
#: where it claims a surface (nodes outside the mask, dark specks fitting noise, may still move).
#: A number off by half its std still lies within 2 std with probability 0.927 (0.954 at its
#: optimum), and that is the worst mask node's; the others move less
CONVERGED_STD = 0.5
