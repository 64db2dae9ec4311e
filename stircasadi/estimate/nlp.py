"""The estimation NLP: OEM / PEM costs, Gaussian / Poisson likelihoods, constraints, IPOPT.

When to use
-----------
``ReflectanceNLP(model, stir, settings, noise)`` assembles, from a set-up ``TransientModel`` and a
measured STIR, the residuals, the cost and the constraints once; ``solve_ipopt`` (here) and
``stircasadi.estimate.lm.solve_lm`` solve it; ``stircasadi.estimate.uncertainty`` reads the
Fisher information at the optimum. The NLP describes; the solver functions solve.

Costs (on the model's support bins S; elsewhere the model is exactly zero)
--------------------------------------------------------------------------
* Gaussian OEM:  f = 1/2 sum_k w_k^2 (y_k - M_k(x))^2 + lambda ||x - x_ref||^2, with
  w_k = 1/sigma (ML; a noise-free twin uses sigma = ``sigma_floor_rel`` x peak) or
  w_k = 1/sqrt(sigma^2 + (rel y_k)^2) (``weighting="relative"``: weak bounces count like strong).
* Gaussian PEM (one-step prediction error): the noise e = y - M is AR(1), e_k = a e_{k-1} + v_k,
  with ``a`` a decision variable; the one-step predictor is yhat_k = M_k + a (y_{k-1} - M_{k-1})
  and f = 1/2 sum (w (y_k - yhat_k))^2 - n_seg/2 log(1 - a^2) (the first bin of each trace
  segment is scaled by sqrt(1 - a^2): the exact AR(1) likelihood). With white noise a -> 0 and
  PEM = OEM, as for any output-error model without process noise.
* Poisson: counts n = s y (s: the capture's photons-per-unit scale), mean mu = s M + b;
  f = sum (mu - n log mu).

Constraints (NLP constraints, not penalties)
--------------------------------------------
bounds 0 <= albedo, specular <= 1, 0 <= exponent; albedo + specular <= 1 on Phong patches;
stability / energy: sum_r rho_r F_{k->r} <= 1 - margin for every patch k (bounds the spectral
radius of the transport below 1); hidden positions in a box of +-eps and
| |p_h - z_v| - D_hv | <= eps for every visible v (D from the geometry stage).
"""
from __future__ import annotations

import time

import casadi as ca
import numpy as np

from ..errors import ModelError, SolverError
from ..model import TransientModel
from .settings import EstimateSettings

_OK_STATUS = ("Solve_Succeeded", "Solved_To_Acceptable_Level")


class ReflectanceNLP:
    """Residuals, cost and constraints of one estimation problem (see the module docstring).

    Parameters
    ----------
    model : a set-up ``TransientModel``.
    stir : measured STIR (n_ill, n_obs, n_bins).
    settings : ``EstimateSettings`` (its ``cost`` and ``constraints`` parts are used).
    noise : the capture's noise attributes (``{"model": "gaussian", "sigma": s}`` or
        ``{"model": "poisson", "scale": s, "background": b}``), or None.
    hidden_distances : optional ``{patch: (visible_patches, D, eps)}``; default: distances at the
        initial positions with ``constraints.hidden_eps``.
    """

    def __init__(self, model: TransientModel, stir, settings: EstimateSettings | None = None,
                 noise: dict | None = None, hidden_distances: dict | None = None):
        if not isinstance(model, TransientModel) or not model.is_setup:
            raise ModelError("ReflectanceNLP needs a TransientModel after setup(); call model.setup().")
        self.settings = (settings or EstimateSettings()).validate()
        self.model = model
        cs = self.settings.cost
        stir = np.asarray(stir, float)
        self.y = model.data_on_support(stir)
        self.noise = dict(noise or {})
        peak = float(np.max(np.abs(stir))) if stir.size else 1.0
        self.peak = peak if peak > 0 else 1.0
        self.sigma, self.sigma_source = self._noise_sigma(stir, cs)
        n = model.n_x
        self.pem = cs.cost == "pem"
        self.poisson = cs.likelihood == "poisson"
        x = model.x
        if self.pem:
            self.a_sym = ca.MX.sym("a_ar1")
            self.xx = ca.vertcat(x, self.a_sym)
        else:
            self.xx = x
        self.n_x = n + int(self.pem)
        self.x_names = list(model.x_names) + (["ar1"] if self.pem else [])
        self.lbx = np.concatenate([model.lbx, [-0.95] if self.pem else []])
        self.ubx = np.concatenate([model.ubx, [0.95] if self.pem else []])
        self.x0 = np.concatenate([model.x0, [0.0] if self.pem else []])
        M = model.y_sym
        if cs.weighting == "noise":
            w = np.full(len(self.y), 1.0 / self.sigma)
        elif cs.weighting == "relative":
            w = 1.0 / np.sqrt(self.sigma ** 2 + (cs.rel_weight * np.abs(self.y)) ** 2)
        else:
            w = np.full(len(self.y), 1.0 / self.peak)
        self.w = w
        self.fold_const = 0.0
        self.n_folded_traces = 0
        self.f_extra = ca.MX(0)
        if self.poisson:
            if self.noise.get("model") != "poisson" or not self.noise.get("scale"):
                raise ModelError("likelihood='poisson' needs the capture's Poisson noise attributes "
                                 f"(model='poisson', scale=photons per STIR unit); got {self.noise}. "
                                 "Use likelihood='gaussian' for this capture.")
            s = float(self.noise["scale"])
            b = float(self.noise.get("background", 0.0)) * s
            counts = np.round(np.maximum(self.y * s, 0.0))
            mu = s * M + b + 1e-300
            self.mu = mu
            self.counts = counts
            self.f_data = ca.sum1(mu - ca.DM(counts) * ca.log(mu))
            self.r = None
        elif cs.fold and not self.pem and model.A_fixed is not None:
            self.r = self._folded_residual(w)
            self.f_data = 0.5 * (ca.sumsqr(self.r) + self.fold_const)
        else:
            r = ca.DM(w) * (ca.DM(self.y) - M)
            if self.pem:
                r = self._whiten_ar1(r)
                n_seg = int(np.count_nonzero(np.diff(model.seg_start)))
                self.f_extra = -0.5 * n_seg * ca.log(1.0 - self.a_sym ** 2)
            self.r = r
            self.f_data = 0.5 * ca.sumsqr(r)
        lam = cs.tikhonov
        self.x_ref = self.x0.copy() if cs.tikhonov_reference == "initial" else np.zeros(self.n_x)
        self.f_reg = lam * ca.sumsqr(x - ca.DM(self.x_ref[:n])) if lam > 0 else ca.MX(0)
        gl = [j for j, (nm, _, _) in enumerate(model.blocks) if nm in ("specular", "exponent")]
        if cs.gloss_prior > 0 and gl:
            self.f_reg = self.f_reg + cs.gloss_prior * ca.sumsqr(x[gl] - ca.DM(model.x0[gl]))
        self.gloss_idx = gl
        self.f = self.f_data + self.f_extra + self.f_reg
        self._build_constraints(hidden_distances)
        self._functions()

    # ------------------------------------------------------------------ pieces
    def _noise_sigma(self, stir, cs):
        floor = cs.sigma_floor_rel * self.peak
        if cs.sigma is not None:
            return max(cs.sigma, floor), "settings"
        if self.noise.get("model") == "gaussian" and self.noise.get("sigma", 0) > 0:
            return max(float(self.noise["sigma"]), floor), "capture"
        mask = np.ones(stir.size, bool)
        mask[self.model.support] = False
        off = stir.reshape(-1)[mask]
        if off.size >= 100 and np.std(off) > 0:
            return max(float(np.std(off)), floor), "off-support bins"
        return floor, "floor (noise-free or unknown; rescaled from residuals for uncertainty)"

    def _general_constraints(self, th):
        """Reciprocity f_kij = f_jik and energy sum_j f_kij a_j cos_i cos_j / d_ij^2 <= 1."""
        m = self.model
        T = m.triples
        F = th["fkij"]
        co_located = np.allclose(m.source, m.camera)
        key = {tuple(t): n for n, t in enumerate(T.tolist())}
        g, lb, ub, names = [], [], [], []
        seen = set()
        for n, (a, i, b) in enumerate(T.tolist()):
            ra, rb = b, a
            if co_located:
                ra = -1 if b == -2 else b
                rb = -2 if a == -1 else a
            partner = key.get((ra, i, rb))
            if partner is None or partner == n or (partner, n) in seen:
                continue
            seen.add((n, partner))
            g.append(F[n] - F[partner])
            lb.append(0.0)
            ub.append(0.0)
            names.append(f"reciprocity {m._triple_name(n)} = {m._triple_name(partner)}")
        # energy: light arriving from a at i, sent to the patches j it sees
        z, nr, ar = m.param("position").value, m.normals, m.areas
        groups: dict = {}
        for n, (a, i, b) in enumerate(T.tolist()):
            if b >= 0:
                groups.setdefault((a, i), []).append((n, b))
        for (a, i), lst in groups.items():
            expr = 0
            for n, b in lst:
                v = z[b] - z[i]
                d = np.linalg.norm(v)
                u = v / d
                w_ = ar[b] * max(np.dot(u, nr[i]), 0) * max(-np.dot(u, nr[b]), 0) / d ** 2
                expr = expr + w_ * F[n]
            g.append(expr)
            lb.append(-np.inf)
            ub.append(1.0)
            names.append(f"energy[{m._end_name(a)}->{m.names[i]}]")
        return g, lb, ub, names

    def _folded_residual(self, w):
        """Residuals folded trace by trace: ||W(y - A a)||^2 = ||Q^T W y - R a||^2 + const.

        A trace whose paths all have constant kernels (fixed geometry) contributes
        W_t (y_t - A_t a_t) with A_t (bins x paths of that trace); its thin QR W_t A_t = Q R
        gives an exactly equivalent residual of length n_paths_t instead of n_bins_t (the
        Fisher information J^T J is unchanged, and no cancellation occurs as it would in the
        normal equations). Traces with symbolic kernels stay bin by bin.
        """
        m = self.model
        A = m.A_fixed.tocsr()
        seg = m.seg_start
        y, wy_all = self.y, w * self.y
        keep_rows, c_vals, R_r, R_c, R_v = [], [], [], [], []
        const, out = 0.0, 0
        n_fold = 0
        for t in range(len(seg) - 1):
            r0, r1 = int(seg[t]), int(seg[t + 1])
            if r1 == r0:
                continue
            lo, hi = A.indptr[r0], A.indptr[r1]
            cols = np.unique(A.indices[lo:hi])
            if m.variable_traces[t] or len(cols) == 0 or len(cols) >= (r1 - r0):
                keep_rows.append(np.arange(r0, r1))
                continue
            blk = A[r0:r1][:, cols].toarray() * w[r0:r1, None]
            Q, R = np.linalg.qr(blk)
            wy = wy_all[r0:r1]
            qy = Q.T @ wy
            const += float(wy @ wy - qy @ qy)
            ii, jj = np.nonzero(R)
            R_r.append(out + ii)
            R_c.append(cols[jj])
            R_v.append(R[ii, jj])
            c_vals.append(qy)
            out += len(cols)
            n_fold += 1
        parts = []
        if out:
            Rb = ca.DM(ca.Sparsity.triplet(out, A.shape[1], np.concatenate(R_r).tolist(),
                                           np.concatenate(R_c).tolist()), np.concatenate(R_v))
            parts.append(ca.DM(np.concatenate(c_vals)) - ca.mtimes(Rb, m.amp_fixed))
        if keep_rows:
            u = np.concatenate(keep_rows)
            Au = A[u].tocsc()
            Aud = ca.DM(ca.Sparsity(Au.shape[0], Au.shape[1], Au.indptr.tolist(), Au.indices.tolist()),
                        Au.data)
            parts.append(ca.DM(w[u]) * (ca.DM(y[u]) - ca.mtimes(Aud, m.amp_fixed) - m.y_var[u.tolist()]))
        self.fold_const = max(const, 0.0)
        self.n_folded_traces = n_fold
        return ca.vertcat(*parts)

    def _whiten_ar1(self, r):
        m = self.model
        n = len(self.y)
        first = np.zeros(n, bool)
        first[m.seg_start[:-1][np.diff(m.seg_start) > 0]] = True
        rows = np.flatnonzero(~first)
        D = ca.DM(ca.Sparsity.triplet(n, n, rows.tolist(), (rows - 1).tolist()), np.ones(len(rows)))
        Fm = ca.DM(first.astype(float))
        a = self.a_sym
        return r - a * ca.mtimes(D, r) + (ca.sqrt(1.0 - a ** 2) - 1.0) * (Fm * r)

    def _build_constraints(self, hidden_distances):
        m, cs = self.model, self.settings.constraints
        th = m.theta_sym
        g, lbg, ubg, names = [], [], [], []
        alb, spec = m.param("albedo"), m.param("specular")
        brdf_free = alb.free | spec.free
        if cs.energy:
            ph = np.flatnonzero(m.glossy & brdf_free)
            if len(ph):
                g.append(th["albedo"][ph.tolist()] + th["specular"][ph.tolist()])
                lbg += [-np.inf] * len(ph)
                ubg += [1.0] * len(ph)
                names += [f"energy[{m.names[k]}]" for k in ph]
        pos = m.param("position")
        if cs.stability and (brdf_free.any() or pos.free.any() or m.param("distance").free.any()):
            c = m.energy_terms(th)
            g.append(c)
            lbg += [-np.inf] * m.M
            ubg += [1.0 - cs.stability_margin] * m.M
            names += [f"stability[{nm}]" for nm in m.names]
        if m.general.any():
            g_, lb_, ub_, nm_ = self._general_constraints(th)
            g += g_
            lbg += lb_
            ubg += ub_
            names += nm_
        dist = m.param("distance")
        hid = np.flatnonzero(pos.free | dist.free)
        if cs.distance_constraints and len(hid):
            Z = th["position"]
            fixed = np.flatnonzero(~(pos.free | dist.free))
            for h in hid:
                if hidden_distances and h in hidden_distances:
                    vs, D, eps = hidden_distances[h]
                    vs = np.asarray(vs, int)
                    D = np.asarray(D, float)
                    eps = np.broadcast_to(np.asarray(eps, float), D.shape)
                else:
                    vs = fixed[~np.isin(fixed, m.anchors[h])]  # anchor distances are bounded unknowns
                    D = np.linalg.norm(pos.value[vs] - pos.value[h], axis=1)
                    eps = np.full(len(vs), cs.hidden_eps)
                if not len(vs):
                    continue
                v = Z[:, vs.tolist()] - ca.repmat(Z[:, int(h)], 1, len(vs))
                g.append(ca.sqrt(ca.sum1(v * v)).T)
                lbg += (D - eps).tolist()
                ubg += (D + eps).tolist()
                names += [f"distance[{m.names[h]},{m.names[v_]}]" for v_ in vs]
        self.g = ca.densify(ca.vertcat(*g)) if g else ca.MX(0, 1)  # IPOPT needs a dense g
        self.lbg, self.ubg = np.array(lbg, float), np.array(ubg, float)
        self.g_names = names

    def _functions(self):
        xx = self.xx
        self.f_cost = ca.Function("f", [xx], [self.f])
        self.f_g = ca.Function("g", [xx], [self.g])
        if self.r is not None:
            self.f_r = ca.Function("r", [xx], [self.r])
            self.f_J = ca.Function("J", [xx], [ca.jacobian(self.r, xx)])
        else:
            self.f_r = self.f_J = None
        My = self.model.y_sym
        self.f_JM = ca.Function("JM", [xx], [ca.jacobian(My, xx)]) if not self.pem else \
            ca.Function("JM", [xx], [ca.horzcat(ca.jacobian(My, self.model.x), ca.DM.zeros(len(self.y), 1))])

    # ------------------------------------------------------------------ evaluation helpers
    def residuals(self, x) -> np.ndarray:
        if self.f_r is None:
            raise ModelError("Residual vectors exist for the Gaussian likelihood only; this NLP is Poisson.")
        return np.asarray(self.f_r(x)).ravel()

    def jacobian(self, x) -> np.ndarray:
        return np.asarray(ca.densify(self.f_J(x)))

    def constraint_violation(self, x) -> float:
        """Largest violation of the bounds and of the constraints at x (0 when feasible)."""
        x = np.asarray(x, float)
        v = max(0.0, float(np.max(self.lbx - x, initial=0.0)), float(np.max(x - self.ubx, initial=0.0)))
        if len(self.lbg):
            gv = np.asarray(self.f_g(x)).ravel()
            v = max(v, float(np.max(self.lbg - gv, initial=0.0)), float(np.max(gv - self.ubg, initial=0.0)))
        return v

    def curvature_scale(self, x) -> np.ndarray:
        """d_j = max(sqrt(F_jj), 1): Gauss-Newton information of each unknown at x (see solve_ipopt)."""
        if self.poisson:
            JM = np.asarray(ca.densify(self.f_JM(x)))
            mu = np.maximum(np.asarray(ca.Function("mu", [self.xx], [self.mu])(x)).ravel(), 1e-300)
            s = float(self.noise["scale"])
            Fd = (s ** 2) * np.sum(JM ** 2 / mu[:, None], axis=0)
        else:
            Fd = np.sum(self.jacobian(x) ** 2, axis=0)
        return np.maximum(np.sqrt(np.maximum(Fd, 0.0)), 1.0)

    def hessian_function(self, kind: str, obj_scale: float = 1.0):
        """CasADi hess_lag for IPOPT: Gauss-Newton J^T J of the data term + exact rest."""
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", self.g.shape[0])
        p = ca.MX.sym("p", 0)
        xx = self.xx
        if self.poisson:
            J = ca.jacobian(self.mu, xx)
            Hd = ca.mtimes(J.T, ca.mtimes(ca.diag(1.0 / self.mu), J))
        else:
            J = ca.jacobian(self.r, xx)
            Hd = ca.mtimes(J.T, J)
        rest = lam_f * obj_scale * (self.f_extra + self.f_reg) + ca.dot(lam_g, self.g)
        H = lam_f * obj_scale * Hd + ca.hessian(rest, xx)[0]
        return ca.Function("hess_gn", [xx, p, lam_f, lam_g], [ca.triu(H)])


def solve_ipopt(nlp: ReflectanceNLP, x0=None, warm: dict | None = None):
    """Solve the NLP with IPOPT (exact, Gauss-Newton or L-BFGS Hessian); return an ``Estimate``.

    ``warm``: a previous ``Estimate.warm_start`` (x, lam_x, lam_g) to restart from. A failed
    solve raises ``SolverError`` (``settings.ipopt.raise_on_failure``) or comes back with
    ``success=False``.
    """
    from .result import Estimate

    st = nlp.settings.ipopt
    opts = {"ipopt.print_level": st.print_level, "print_time": False, "ipopt.tol": st.tol,
            "ipopt.max_iter": st.max_iter, "ipopt.sb": "yes", "ipopt.honor_original_bounds": "yes",
            "ipopt.acceptable_tol": st.acceptable_tol, "ipopt.acceptable_iter": 10}
    x_init = np.asarray(warm["x"] if warm else (nlp.x0 if x0 is None else x0), float)
    x_init = np.clip(x_init, nlp.lbx, nlp.ubx)
    t0 = time.perf_counter()
    # Curvature scaling: IPOPT works on xi = d * x with d_j = max(sqrt(F_jj(x0)), 1), F the
    # Gauss-Newton information, so a first-bounce albedo (F ~ 1e18) and a 1e-6 third-bounce one
    # (F ~ 1e6) look alike to its tolerances: tol is then "a fraction of one standard deviation".
    d = nlp.curvature_scale(x_init) if st.curvature_scaling else np.ones(nlp.n_x)
    opts["ipopt.nlp_scaling_method"] = "none" if st.curvature_scaling else "gradient-based"
    xi = ca.MX.sym("xi", nlp.n_x)
    fg = ca.Function("fg", [nlp.xx], [nlp.f, nlp.g])
    f_xi, g_xi = fg(xi / ca.DM(d))
    if st.hessian == "limited-memory":
        opts["ipopt.hessian_approximation"] = "limited-memory"
    elif st.hessian == "gauss-newton":
        hx = nlp.hessian_function("gauss-newton")
        lam_f = ca.MX.sym("lam_f")
        lam_g = ca.MX.sym("lam_g", nlp.g.shape[0])
        p = ca.MX.sym("p", 0)
        Dinv = ca.diag(ca.DM(1.0 / d))
        Hxi = ca.mtimes(Dinv, ca.mtimes(ca.triu2symm(hx(xi / ca.DM(d), p, lam_f, lam_g)), Dinv))
        opts["hess_lag"] = ca.Function("hess_xi", [xi, p, lam_f, lam_g], [ca.triu(Hxi)])
    if warm:
        opts["ipopt.warm_start_init_point"] = "yes"
        opts["ipopt.mu_init"] = 1e-6
        opts["ipopt.warm_start_bound_push"] = 1e-9
        opts["ipopt.warm_start_mult_bound_push"] = 1e-9
    for k, v in st.extra.items():
        opts[k if k.startswith("ipopt.") else f"ipopt.{k}"] = v
    solver = ca.nlpsol("reflectance", "ipopt", {"x": xi, "f": f_xi, "g": g_xi}, opts)
    t_build = time.perf_counter() - t0
    args = dict(x0=x_init * d, lbx=nlp.lbx * d, ubx=nlp.ubx * d, lbg=nlp.lbg, ubg=nlp.ubg)
    if warm:
        args["lam_x0"] = np.asarray(warm.get("lam_x", np.zeros(nlp.n_x))) / d
        args["lam_g0"] = warm.get("lam_g", 0)
    t1 = time.perf_counter()
    sol = solver(**args)
    t_solve = time.perf_counter() - t1
    stats = solver.stats()
    status = stats.get("return_status", "unknown")
    success = bool(stats.get("success", False)) and status in _OK_STATUS
    x = np.asarray(sol["x"]).ravel() / d
    info = {"status": status, "iterations": int(stats.get("iter_count", -1)), "success": success,
            "hessian": st.hessian, "build_time_s": t_build, "solve_time_s": t_solve,
            "cost": float(sol["f"]), "curvature_scale_range": [float(d.min()), float(d.max())],
            "constraint_violation": nlp.constraint_violation(x)}
    est = Estimate.from_solution(nlp, x, solver="ipopt", info=info,
                                 warm_start={"x": x, "lam_x": np.asarray(sol["lam_x"]).ravel() * d,
                                             "lam_g": np.asarray(sol["lam_g"]).ravel()})
    if not success and st.raise_on_failure:
        raise SolverError(f"IPOPT did not converge: return_status '{status}' after "
                          f"{info['iterations']} iterations (cost {info['cost']:.6g}). Allowed: "
                          f"{_OK_STATUS}. Try a better initial guess, hessian='exact', more "
                          "max_iter, or check that the data match the model (bounces, IRF).",
                          status=status, stats=info)
    return est
