"""``JointEstimate``: every reported number with its std, identifiability and provenance.

A failed solve is never presented as a result: ``success`` is False. A number the data cannot
identify keeps its solver value in ``values`` but is reported as None with the reason in
``notes``; a number that was given (known wall points, calibrated normals, declared areas) has
std 0 and a note saying where it came from.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .uncertainty import QUANTITIES, fisher, report_function

__all__ = ["JointEstimate", "assemble"]

_ANGLE_NAMES = ("normal",)
#: relative floor of a reported std (double precision's resolution of the computed numbers)
_STD_FLOOR = 1e-12


@dataclass
class JointEstimate:
    """Result of a joint solve (see the module docstring).

    values, std : name -> (M,) or (M, 3) arrays for the names of ``QUANTITIES``.
    identifiable : name -> (M,) bool. free : name -> (M,) bool (estimated here).
    notes : (patch index, name) -> reason (unidentifiable) or source (given).
    cov_q : covariance of the reported numbers (names ``q_names``), inflation applied.
    """

    values: dict
    std: dict
    identifiable: dict
    free: dict
    notes: dict
    q_names: list
    cov_q: np.ndarray
    x: np.ndarray
    x_names: list
    success: bool
    status: str
    iterations: int
    solver: str
    chi2: float
    dof: int
    inflation: float
    sigma: float
    sigma_source: str
    flags: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / max(self.dof, 1)


def _thresholds(us, name, value):
    """Largest std at which a number still counts as identified."""
    if name == "albedo":
        return us.max_rel_std
    if name == "specular":
        return us.max_rel_std
    if name == "exponent":
        return us.max_rel_std * 500.0
    if name in ("area", "albedo_area"):
        return us.max_rel_std * max(abs(value), 1e-12)
    if name == "normal":
        return np.radians(us.max_tilt_std_deg)
    if name == "position":
        return us.max_position_std if us.max_position_std is not None else 0.05
    return np.inf


def assemble(nlp, sol, names, given: dict | None = None, prior_info=None, flags=None) -> JointEstimate:
    """Build the ``JointEstimate`` of a finished solve ``sol`` of ``nlp``.

    ``given``: (name -> (M,) bool) numbers that were inputs (std 0, noted); ``names``: patch
    labels (for messages)."""
    model = nlp.model
    us = nlp.settings.uncertainty
    M = model.M
    f, layout = report_function(model)
    q, Jq = (np.asarray(v) for v in f(sol.x[:model.n_x]))
    q = q.ravel()
    Jq = np.asarray(Jq)
    if nlp.pem:
        Jq = np.hstack([Jq, np.zeros((len(q), 1))])
    if prior_info is None and getattr(nlp, "r_prior", None) is not None:
        Jp = nlp.prior_jacobian(sol.x)
        prior_info = np.asarray((Jp.T @ Jp).todense())
    unc = fisher(nlp, sol.x, prior_info, frozen=getattr(nlp, "frozen", None))
    cov_x = unc["cov_x"]
    cov_q = Jq @ cov_x @ Jq.T
    var_q = np.maximum(np.diag(cov_q), 0.0)
    touch = np.zeros(len(q), bool)  # null directions are in cov_x through the weak prior
    given = given or {}
    free_x = {n: np.zeros(M, bool) for n, _ in QUANTITIES}
    for j, (n, k, _) in enumerate(model.blocks):
        if n == "position":
            free_x["position"][k] = True
        elif n in ("tilt", "tilt2"):
            free_x["normal"][k] = True
        elif n in ("albedo", "area", "specular", "exponent"):
            free_x[n][k] = True
    # a number is estimated when it depends on x
    dep = np.linalg.norm(Jq, axis=1) > 0
    values, std, ident, free, notes = {}, {}, {}, {}, {}
    q_names = []
    for name, width in QUANTITIES:
        off, _ = layout[name]
        sl = slice(off, off + width * M)
        v = q[sl].reshape(M, width) if width > 1 else q[sl]
        s = np.sqrt(var_q[sl]).reshape(M, width) if width > 1 else np.sqrt(var_q[sl])
        d = dep[sl].reshape(M, width).any(axis=1) if width > 1 else dep[sl]
        # no estimated number is known better than the arithmetic: a component a prior or a
        # basis holds exactly (flatland, a camera ray) gets this floor, not a zero std
        floor = _STD_FLOOR * np.maximum(np.abs(v), 1.0)
        s = np.where(d[:, None] if width > 1 else d, np.maximum(s, floor), s)
        t = touch[sl].reshape(M, width).any(axis=1) if width > 1 else touch[sl]
        ok = np.ones(M, bool)
        for k in range(M):
            q_names += [f"{name}[{names[k]}]" + ("" if width == 1 else f".{'xyz'[c]}") for c in range(width)]
            if not d[k]:
                continue
            sk = float(np.linalg.norm(s[k])) if width > 1 else float(s[k])
            lim = _thresholds(us, name, float(np.linalg.norm(v[k])) if width > 1 else float(v[k]))
            if t[k]:
                ok[k] = False
                notes[(k, name)] = "the data do not constrain it (a null direction of the Fisher information)"
            elif not np.isfinite(sk) or sk > lim:
                ok[k] = False
                notes[(k, name)] = f"std {sk:.3g} exceeds the identifiability limit {lim:.3g}"
        for k in np.flatnonzero(given.get(name, np.zeros(M, bool))):
            notes.setdefault((k, name), "given")
        values[name], std[name], ident[name], free[name] = v, s, ok, d
    # a hidden disc's area is resolved only when its spread is significantly above none: at its
    # lower bound, or within 2 std of it, the data say "smaller than the resolution", not a size
    A = model.param("area")
    for k in np.flatnonzero(model.albedo_product & A.free):
        a, sa = float(values["area"][k]), float(std["area"][k])
        if a - A.lower[k] < 2.0 * sa or a <= A.lower[k] * (1 + 1e-6):
            ident["area"][k] = False
            notes[(k, "area")] = (f"the extent is not resolved by the data (area below {a + 2 * sa:.3g} m^2 "
                                  "at 2 sigma: smaller than the transient resolution)")
    # albedo of a patch whose unknown is albedo x area: only where the area is identified
    for k in np.flatnonzero(model.albedo_product):
        if not (free["area"][k] and ident["area"][k]) and not given.get("area", np.zeros(M, bool))[k]:
            ident["albedo"][k] = False
            notes[(k, "albedo")] = ("third bounces identify albedo x area only; its area (extent) is not "
                                    "resolved by the data — give it (--areas) to get the albedo")
            if not free["area"][k] or not ident["area"][k]:
                ident["area"][k] = False
                notes.setdefault((k, "area"), "the extent of the hidden patch is not resolved by the data")
    n_f = len(model.triples)
    if n_f:  # the general BRDF's tabulated values (unknowns of x themselves)
        j0 = model.params.n_x
        sf = np.sqrt(np.maximum(np.diag(cov_x)[j0:j0 + n_f], 0.0)) * model.fkij_scale
        values["fkij"] = sol.x[j0:j0 + n_f] * model.fkij_scale
        std["fkij"] = sf
        ident["fkij"] = np.isfinite(sf) & (sf < us.max_rel_std * model.general_bounds[1])
        free["fkij"] = np.ones(n_f, bool)
    fl = list(flags or [])
    frozen = set(getattr(nlp, "frozen", []) or [])
    if frozen:
        fl.append("held at their start (the data cannot separate them): "
                  + ", ".join(nlp.x_names[j] for j in sorted(frozen)))
    for j in np.flatnonzero(unc["at_bound"][:model.n_x]):
        if j not in frozen:
            fl.append(f"{nlp.x_names[j]} sits on a bound: its interval is the unconstrained one.")
    if not sol.success:
        fl.insert(0, f"FAILED: {sol.status}")
    if unc["inflation"] > 1.0 and not nlp.sigma_source.startswith("floor"):
        fl.append(f"model mismatch: chi2/dof = {unc['chi2_dof']:.3g} > 1; every std is multiplied by "
                  f"{unc['inflation']:.3g}.")
    return JointEstimate(values=values, std=std, identifiable=ident, free=free, notes=notes,
                         q_names=q_names, cov_q=cov_q, x=np.asarray(sol.x), x_names=list(nlp.x_names),
                         success=bool(sol.success), status=str(sol.status), iterations=int(sol.iterations),
                         solver=sol.solver, chi2=unc["chi2"], dof=unc["dof"], inflation=unc["inflation"],
                         sigma=unc["sigma_used"], sigma_source=nlp.sigma_source, flags=fl,
                         timings={"solve_s": sol.solve_time_s, "solver_build_s": sol.build_time_s,
                                  "model_build_s": model.info.build_time_s},
                         extra={"null_dim": unc["null_dim"], "free_x": free_x, "cov_x": cov_x, "null_x": unc["null"], "cost": float(sol.cost),
                                "ar1": float(sol.x[-1]) if nlp.pem else None, "solution": sol,
                                "model": {"n_paths": model.info.n_paths,
                                          "n_variable_paths": model.info.n_variable_paths,
                                          "n_support_bins": model.info.n_support,
                                          "bounces": model.bounces, "n_vertices": model.info.n_vertices}})


def patch_records(est: JointEstimate, ids, visible, names, brdf: str = "lambertian") -> list[dict]:
    """The estimate.json ``patches`` list (docs/estimate-json.md): per patch its numbers with
    ``_std``, null where not identified (reason in ``notes``), ``unidentifiable`` names."""
    out = []
    for k in range(len(ids)):
        p = {"id": int(ids[k]), "name": names[k], "visible": bool(visible[k])}
        notes, unid = {}, []
        keys = ["position", "normal", "area", "albedo", "albedo_area"]
        if brdf == "phong" and visible[k]:
            keys += ["specular", "exponent"]
        for q in keys:
            v, s = est.values[q][k], est.std[q][k]
            note = est.notes.get((k, q))
            given = note == "given"
            if q in ("specular", "exponent") and not est.free[q][k]:
                p[q] = p[f"{q}_std"] = None   # selected Lambertian: no Phong lobe to report
                notes[q] = "Lambertian: the data show no gloss (likelihood-ratio test)"
                continue
            if not est.free[q][k] and not given:
                p[q] = None
                p[f"{q}_std"] = None
                notes[q] = note or "not estimated"
                unid.append(q)
                continue
            if est.identifiable[q][k] or given:
                p[q] = np.asarray(v).tolist()
                p[f"{q}_std"] = (np.zeros_like(np.asarray(s)) if given else np.asarray(s)).tolist()
                if note:
                    notes[q] = note
            else:
                p[q] = None
                p[f"{q}_std"] = None
                notes[q] = note or "not identified"
                unid.append(q)
        if not visible[k]:
            a = p.get("area")
            p["extent"] = None if a is None else float(np.sqrt(a))
            p["extent_std"] = None if a is None else float(p["area_std"] / (2 * np.sqrt(a)))
        if unid:
            p["unidentifiable"] = unid
        p["notes"] = notes
        out.append(p)
    return out
