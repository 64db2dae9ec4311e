"""The estimation NLP: OEM / PEM costs, Gaussian / Poisson likelihoods, on a set-up model.

``JointNLP(model, stir, settings, sigma)`` assembles, once, the residuals, the cost and the
constraints (``joint/constraints.py``); ``joint/solve.py`` (IPOPT) and ``joint/lm.py`` solve it,
``joint/uncertainty.py`` reads its Fisher information. It uses the model's documented
``OutputStructure`` only. The NLP describes; the solver functions solve.

Costs (on the model's support bins; elsewhere the model is exactly zero)
-------------------------------------------------------------------------
* Gaussian OEM:  f = 1/2 sum_k w_k^2 (y_k - M_k(x))^2 + lambda ||x - x_ref||^2, with
  w_k = 1/sigma (maximum likelihood), or 1/sqrt(sigma^2 + (rel y_k)^2) (``weighting="relative"``).
  Traces whose paths all have constant kernels are folded exactly by a per-trace QR
  (``_folded_residual``): the same cost and Jacobian products with n_paths rows instead of n_bins.
* Gaussian PEM (one-step prediction error): the noise e = y - M is AR(1), e_k = a e_{k-1} + v_k,
  with ``a`` a decision variable: f = 1/2 sum (w (y_k - yhat_k))^2 - n_seg/2 log(1 - a^2) (the
  exact AR(1) likelihood). With white noise a -> 0 and PEM = OEM.
* Poisson: counts n = s y (s: photons per STIR unit), mean mu = s M + b: f = sum (mu - n log mu).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from ..errors import ModelError
from .constraints import build_constraints
from .settings import EstimateSettings

__all__ = ["JointNLP"]


class JointNLP:
    """Residuals, cost and constraints of one estimation problem (see the module docstring).

    Parameters
    ----------
    model : a set-up ``TransientModel``.
    stir : measured STIR (n_ill, n_obs, n_bins).
    settings : ``EstimateSettings``.
    sigma : noise std (STIR units) and where it came from; None: from ``noise`` or a floor.
    noise : the capture's noise attributes (Poisson: ``scale``, ``background``).
    gauge : optional (G, x0): linear equality G (x - x0) = 0 fixing a free frame.
    flat : optional (P, 2) patch pairs (k, j) of flat groups: the flatness prior
        n_k . (z_j - z_k) / |z_j - z_k| ~ N(0, sin 1 deg), each normal perpendicular to the
        directions to its group's patches — added to the cost and to the Fisher information (it
        couples normals to positions: unidentified positions leave the normals unidentified).
    """

    def __init__(self, model, stir, settings: EstimateSettings | None = None, sigma=None,
                 noise: dict | None = None, gauge=None, flat=None):
        if not getattr(model, "is_setup", False):
            raise ModelError("JointNLP needs a TransientModel after setup(); call model.setup().")
        self.settings = (settings or EstimateSettings()).validate()
        self.model = model
        out = model.output
        self.out = out
        cs = self.settings.cost
        stir = np.asarray(stir, float)
        self.y = model.data_on_support(stir)
        self.noise = dict(noise or {})
        self.budget = None   # a ``budget.Budget`` the solvers stop at (set by ``fit_joint``)
        peak = float(np.max(np.abs(stir))) if stir.size else 1.0
        self.peak = peak if peak > 0 else 1.0
        floor = cs.sigma_floor_rel * self.peak
        if cs.sigma is not None:
            sigma = (cs.sigma, "settings")
        elif sigma is None:
            s = self.noise.get("sigma") if self.noise.get("model") == "gaussian" else None
            sigma = (float(s), "capture") if s else (floor, "floor (noise-free or unknown)")
        self.sigma = max(float(sigma[0]), floor)
        self.sigma_source = sigma[1] if float(sigma[0]) >= floor else "floor (noise-free or unknown)"
        self.pem = cs.cost == "pem"
        self.poisson = cs.likelihood == "poisson"
        x = model.x
        n = model.n_x
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
        M = out.y
        if cs.weighting == "noise":
            w = np.full(len(self.y), 1.0 / self.sigma)
        elif cs.weighting == "relative":
            w = 1.0 / np.sqrt(self.sigma ** 2 + (cs.rel_weight * np.abs(self.y)) ** 2)
        elif cs.weighting == "counts":
            sc = float(self.noise.get("scale") or 1.0)
            w = sc / np.sqrt(np.maximum(sc * self.y, 1.0))
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
            self.counts = np.round(np.maximum(self.y * s, 0.0))
            self.mu = ca.fmax(s * M + b, 1e-9)
            self.f_data = ca.sum1(self.mu - ca.DM(self.counts) * ca.log(self.mu))
            self.r = None
        elif cs.fold and not self.pem and out.A_fixed is not None:
            self.r = self._folded_residual(w)
            self.f_data = 0.5 * (ca.sumsqr(self.r) + self.fold_const)
        else:
            r = ca.DM(w) * (ca.DM(self.y) - M)
            if self.pem:
                r = self._whiten_ar1(r)
                n_seg = int(np.count_nonzero(np.diff(out.seg_start)))
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
        self.r_prior = None
        if flat is not None and len(flat):
            from ..model.vertices import patch_quantities

            pq = patch_quantities(model.theta_sym, model)
            k, j = np.asarray(flat)[:, 0].tolist(), np.asarray(flat)[:, 1].tolist()
            dz = [pq["z"][c][:, j] - pq["z"][c][:, k] for c in range(3)]
            nrm = ca.sqrt(dz[0] * dz[0] + dz[1] * dz[1] + dz[2] * dz[2])
            cosv = (pq["n"][0][:, k] * dz[0] + pq["n"][1][:, k] * dz[1] + pq["n"][2][:, k] * dz[2]) / nrm
            self.r_prior = (cosv / np.sin(np.radians(1.0))).T
            self.f_reg = self.f_reg + 0.5 * ca.sumsqr(self.r_prior)
        if cs.weak_prior:
            # the weak prior of uncertainty.PRIOR_RANGE: directions the data do not see stay at
            # the start instead of wandering (negligible where the data inform)
            from .uncertainty import prior_std_x

            ps = prior_std_x(self)[:n]
            self.f_reg = self.f_reg + 0.5 * ca.sumsqr((x - ca.DM(model.x0)) / ca.DM(ps))
        self.f = self.f_data + self.f_extra + self.f_reg
        self.g, self.lbg, self.ubg, self.g_names = build_constraints(model, self.settings, gauge)
        self._functions()

    # ------------------------------------------------------------------ pieces
    def _folded_residual(self, w):
        """Residuals folded trace by trace: ||W(y - A a)||^2 = ||Q^T W y - R a||^2 + const.

        A trace whose paths all have constant kernels contributes W_t (y_t - A_t a_t); its thin
        QR W_t A_t = Q R gives an exactly equivalent residual of length n_paths_t (the Fisher
        information J^T J is unchanged). Traces with symbolic kernels stay bin by bin.
        """
        out_, y = self.out, self.y
        A = out_.A_fixed.tocsr()
        seg = out_.seg_start
        wy_all = w * y
        keep_rows, c_vals, R_r, R_c, R_v = [], [], [], [], []
        const, n_out, n_fold = 0.0, 0, 0
        for t in range(len(seg) - 1):
            r0, r1 = int(seg[t]), int(seg[t + 1])
            if r1 == r0:
                continue
            cols = np.unique(A.indices[A.indptr[r0]:A.indptr[r1]])
            if out_.variable_traces[t] or len(cols) == 0 or len(cols) >= (r1 - r0):
                keep_rows.append(np.arange(r0, r1))
                continue
            blk = A[r0:r1][:, cols].toarray() * w[r0:r1, None]
            Q, R = np.linalg.qr(blk)
            wy = wy_all[r0:r1]
            qy = Q.T @ wy
            const += float(wy @ wy - qy @ qy)
            ii, jj = np.nonzero(R)
            R_r.append(n_out + ii)
            R_c.append(cols[jj])
            R_v.append(R[ii, jj])
            c_vals.append(qy)
            n_out += len(cols)
            n_fold += 1
        parts = []
        if n_out:
            Rb = ca.DM(ca.Sparsity.triplet(n_out, A.shape[1], np.concatenate(R_r).tolist(),
                                           np.concatenate(R_c).tolist()), np.concatenate(R_v))
            parts.append(ca.DM(np.concatenate(c_vals)) - ca.mtimes(Rb, out_.amp_fixed))
        if keep_rows:
            u = np.concatenate(keep_rows)
            Au = A[u].tocsc()
            Aud = ca.DM(ca.Sparsity(Au.shape[0], Au.shape[1], Au.indptr.tolist(), Au.indices.tolist()),
                        Au.data)
            parts.append(ca.DM(w[u]) * (ca.DM(y[u]) - ca.mtimes(Aud, out_.amp_fixed) - out_.y_var[u.tolist()]))
        self.fold_const = max(const, 0.0)
        self.n_folded_traces = n_fold
        return ca.vertcat(*parts)

    def _whiten_ar1(self, r):
        n = len(self.y)
        seg = self.out.seg_start
        first = np.zeros(n, bool)
        first[seg[:-1][np.diff(seg) > 0]] = True
        rows = np.flatnonzero(~first)
        D = ca.DM(ca.Sparsity.triplet(n, n, rows.tolist(), (rows - 1).tolist()), np.ones(len(rows)))
        Fm = ca.DM(first.astype(float))
        a = self.a_sym
        return r - a * ca.mtimes(D, r) + (ca.sqrt(1.0 - a ** 2) - 1.0) * (Fm * r)

    def _functions(self):
        xx = self.xx
        self.f_cost = ca.Function("f", [xx], [self.f])
        self.f_g = ca.Function("g", [xx], [self.g])
        if self.r is not None:
            self.f_r = ca.Function("r", [xx], [self.r])
            self.f_J = ca.Function("J", [xx], [ca.jacobian(self.r, xx)])
        else:
            self.f_r = self.f_J = None
        if self.r_prior is not None:
            self.f_Jp = ca.Function("Jp", [xx], [ca.jacobian(self.r_prior, xx)])
        self.f_M = ca.Function("M", [xx], [self.out.y])

    @property
    def f_JM(self):
        """Jacobian of the model STIR on the support (built on first use)."""
        if getattr(self, "_f_JM", None) is None:
            jm = ca.jacobian(self.out.y, self.model.x)
            if self.pem:
                jm = ca.horzcat(jm, ca.DM.zeros(len(self.y), 1))
            self._f_JM = ca.Function("JM", [self.xx], [jm])
        return self._f_JM

    # ------------------------------------------------------------------ evaluation helpers
    def residuals(self, x) -> np.ndarray:
        if self.f_r is None:
            raise ModelError("Residual vectors exist for the Gaussian likelihood only; this NLP is Poisson.")
        return np.asarray(self.f_r(x)).ravel()

    def jacobian(self, x) -> np.ndarray:
        return np.asarray(ca.densify(self.f_J(x)))

    def jacobian_sparse(self, x):
        """The residuals' Jacobian at x as a scipy CSC matrix (never densified)."""
        return _to_scipy(self.f_J(x))

    def information(self, x) -> np.ndarray:
        """J^T J (n_x, n_x) of the data residuals, computed sparsely."""
        J = self.jacobian_sparse(x)
        return np.asarray((J.T @ J).todense())

    def prior_jacobian(self, x):
        """Jacobian of the flatness prior's residuals (CSC), or None."""
        return _to_scipy(self.f_Jp(x)) if self.r_prior is not None else None

    def model_values(self, x) -> np.ndarray:
        """The model STIR on the support at x."""
        return np.asarray(self.f_M(x)).ravel()

    def bin_std(self, pred):
        """Noise std of each bin given the model's prediction ``pred`` (any shape): sigma for
        Gaussian noise; sqrt(max(s M + b, 1)) / s for photon counts (s counts per STIR unit)."""
        if not (self.poisson or self.settings.cost.weighting == "counts"):
            return self.sigma
        s = float(self.noise.get("scale") or 1.0)
        b = float(self.noise.get("background", 0.0)) * s
        return np.sqrt(np.maximum(s * np.asarray(pred) + b, 1.0)) / s

    def whiten(self, data, pred):
        """(data - pred) / noise std, elementwise (full STIRs or support vectors)."""
        return (np.asarray(data) - np.asarray(pred)) / self.bin_std(pred)

    def whitened_residuals(self, x) -> np.ndarray:
        """Whitened residuals on every support bin (unfolded), for the self-checks."""
        M = self.model_values(x)
        return self.whiten(self.y, M)

    def constraint_violation(self, x) -> float:
        """Largest violation of the bounds and of the constraints at x (0 when feasible)."""
        x = np.asarray(x, float)
        v = max(0.0, float(np.max(self.lbx - x, initial=0.0)), float(np.max(x - self.ubx, initial=0.0)))
        if len(self.lbg):
            gv = np.asarray(self.f_g(x)).ravel()
            v = max(v, float(np.max(self.lbg - gv, initial=0.0)), float(np.max(gv - self.ubg, initial=0.0)))
        return v

    def curvature_scale(self, x) -> np.ndarray:
        """d_j = max(sqrt(F_jj), 1): Gauss-Newton information of each unknown at x."""
        if self.poisson:
            JM = np.asarray(ca.densify(self.f_JM(x)))
            mu = np.maximum(np.asarray(ca.Function("mu", [self.xx], [self.mu])(x)).ravel(), 1e-300)
            s = float(self.noise["scale"])
            Fd = (s ** 2) * np.sum(JM ** 2 / mu[:, None], axis=0)
        else:
            J = self.f_J(x)
            Fd = np.asarray(ca.sum1(J * J)).ravel() if hasattr(J, "nnz") else np.sum(np.asarray(J) ** 2, axis=0)
        return np.maximum(np.sqrt(np.maximum(Fd, 0.0)), 1.0)

    def hessian_function(self, obj_scale: float = 1.0):
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


def _to_scipy(M):
    """A CasADi DM (sparse) as a scipy CSC matrix."""
    from scipy import sparse

    sp = M.sparsity()
    return sparse.csc_matrix((np.asarray(M.nonzeros(), float), np.asarray(sp.row(), int),
                              np.asarray(sp.colind(), int)), shape=(sp.size1(), sp.size2()))
