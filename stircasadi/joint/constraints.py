"""Hard physical constraints of the joint NLP (constraints, never penalties; DESIGN.md section 6).

* Phong energy: albedo + specular <= 1 on every glossy patch with a free lobe;
* transport stability: every flux-transfer column sum sum_r rho_r F_{k->r} <= 1 - margin
  (``TransientModel.energy_terms``), which bounds the spectral radius of the transport below 1;
* general BRDF (the paper's f_kij): Helmholtz reciprocity f_kij = f_jik (source and camera one
  direction when co-located) and energy sum_j f_kij a_j cos_i cos_j / d_ij^2 <= 1;
* gauge: where the frame is free (positions known only up to a rotation about the source), the
  linearised inner constraints G^T (x - x0) = 0 remove the rotation from the solve.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

__all__ = ["build_constraints"]


def build_constraints(model, settings, gauge=None):
    """(g MX (dense), lbg, ubg, names, n_equality_rows) for the set-up ``model``."""
    cs = settings.constraints
    th = model.theta_sym
    g, lbg, ubg, names = [], [], [], []
    alb, spec = model.param("albedo"), model.param("specular")
    brdf_free = alb.free | spec.free
    if cs.energy:
        ph = np.flatnonzero(model.glossy & brdf_free)
        if len(ph):
            g.append(th["albedo"][ph.tolist()] + th["specular"][ph.tolist()])
            lbg += [-np.inf] * len(ph)
            ubg += [1.0] * len(ph)
            names += [f"energy[{model.names[k]}]" for k in ph]
    moving = model.param("position").free.any() or model.param("area").free.any() or model.tilt_free.any()
    if cs.stability and (brdf_free.any() or moving) and model.visibility.any():
        g.append(model.energy_terms())
        lbg += [-np.inf] * model.M
        ubg += [1.0 - cs.stability_margin] * model.M
        names += [f"stability[{nm}]" for nm in model.names]
    if model.general.any():
        g_, lb_, ub_, nm_ = _general(model)
        g += g_
        lbg += lb_
        ubg += ub_
        names += nm_
    if gauge is not None and len(gauge[0]):
        G, x0 = gauge
        g.append(ca.mtimes(ca.DM(G), model.x - ca.DM(x0)))
        lbg += [0.0] * len(G)
        ubg += [0.0] * len(G)
        names += [f"gauge[{k}]" for k in range(len(G))]
    gg = ca.densify(ca.vertcat(*g)) if g else ca.MX(0, 1)  # IPOPT needs a dense g
    return gg, np.array(lbg, float), np.array(ubg, float), names


def _general(model):
    """Reciprocity f_kij = f_jik and energy sum_j f_kij a_j cos_i cos_j / d_ij^2 <= 1."""
    T = model.triples
    F = model.x[model.params.n_x:model.params.n_x + len(T)] * model.fkij_scale
    co_located = np.allclose(model.source, model.camera)
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
        names.append(f"reciprocity {model.triple_name(n)} = {model.triple_name(partner)}")
    z, nr, ar = model.param("position").value, model.normals, model.param("area").value
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
        names.append(f"energy[{model.end_name(a)}->{model.names[i]}]")
    return g, lb, ub, names
