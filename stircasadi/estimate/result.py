"""``Estimate``: BRDF parameters and hidden geometry with standard deviations, status and timings.

A failed solve is never presented as a result: ``success`` is False and every printer and the
JSON say FAILED (solvers raise ``SolverError`` by default). An unknown the data cannot identify
keeps its solver value in ``solver_values`` but is reported as None with the reason.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_BRDF_NAMES = ("albedo", "specular", "exponent")


@dataclass
class Estimate:
    """Result of a reflectance / joint-geometry solve.

    Attributes
    ----------
    values : name -> array over the model's patches ((M,) or (M, 3) for positions): the final
        parameters (fixed ones included).
    std : same shapes; NaN where the quantity was fixed, inf where unidentifiable.
    free : name -> (M,) bool, where the quantity was unknown.
    identifiable : name -> (M,) bool (True where fixed).
    corr : correlation matrix of the unknowns (order ``x_names``).
    success, status, iterations, solver, timings, cost, sigma : the solve.
    ids, visible, names : patch ids (capture / geometry ids), visibility, labels.
    """

    values: dict
    std: dict
    free: dict
    identifiable: dict
    x: np.ndarray
    x_names: list
    corr: np.ndarray
    success: bool
    status: str
    iterations: int
    solver: str
    timings: dict
    cost: float
    sigma: float
    ids: np.ndarray
    visible: np.ndarray
    names: list
    normals: np.ndarray
    glossy: np.ndarray
    info: dict = field(default_factory=dict)
    warm_start: dict | None = None
    flags: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    @classmethod
    def from_solution(cls, nlp, x, solver: str, info: dict, warm_start=None) -> "Estimate":
        from .uncertainty import fisher_uncertainty

        m = nlp.model
        x = np.asarray(x, float)
        theta = m.theta(x[:m.n_x])
        std = {n: np.full_like(v, np.nan, dtype=float) for n, v in theta.items()}
        ident = {n: np.ones(len(v), bool) for n, v in theta.items()}
        free = {n: m.param(n).free.copy() for n in theta if n != "normal"}
        free["position"] = free["position"] | free["distance"]
        free["normal"] = m.tilt_free.copy()
        flags = []
        unc = None
        if nlp.settings.uncertainty.compute:
            unc = fisher_uncertainty(nlp, x)
            for j, (n, k, c) in enumerate(m.blocks):
                s = unc["std_theta"][j]
                if std[n].ndim == 1:
                    std[n][k] = s
                else:
                    std[n][k, c] = s
                if not unc["identifiable"][j]:
                    ident[n][k] = False
            for n in theta:
                if n == "normal":
                    continue
                for k in np.flatnonzero(~ident[n]):
                    what = m._triple_name(k) if n == "fkij" else f"{n} of patch {m.names[k]}"
                    flags.append(f"{what} is not identifiable from the data "
                                 f"(std {np.max(np.atleast_1d(std[n][k])):.3g}).")
            for k, sp in unc["position_std_from_distances"].items():
                std["position"][k] = sp if ident["distance"][k] else np.inf
                ident["position"][k] = ident["distance"][k]
            for k, sn in unc["normal_std"].items():
                ok = bool(ident["tilt"][k] and ident["tilt2"][k])
                std["normal"][k] = sn if ok else np.inf
                ident["normal"][k] = ok
            for j in np.flatnonzero(unc["at_bound"][:m.n_x]):
                flags.append(f"{m.x_names[j]} sits on a bound: its interval is the unconstrained one.")
            corr = unc["corr"]
        else:
            corr = np.full((nlp.n_x, nlp.n_x), np.nan)
        if not info.get("success", False):
            flags.insert(0, f"FAILED: {info.get('status')}")
        ids = getattr(m, "ids", None)
        ids = np.arange(m.M) if ids is None else np.asarray(ids)
        visible = np.zeros(m.M, bool)
        visible[m.obs_ids] = True
        visible[m.ill_ids] = True
        extra = {"model": {"n_paths": m.info.n_paths, "n_variable_paths": m.info.n_variable_paths,
                           "n_support_bins": m.info.n_support, "bounces": m.bounces,
                           "build_time_s": m.info.build_time_s},
                 "sigma_source": nlp.sigma_source}
        if nlp.pem:
            extra["ar1"] = float(x[-1])
        if unc is not None:
            extra["fisher_null_dim"] = unc["null_dim"]
            extra["sigma_used"] = unc["sigma_used"]
        timings = {"model_build_s": m.info.build_time_s, "solver_build_s": info.get("build_time_s", 0.0),
                   "solve_s": info.get("solve_time_s", 0.0)}
        return cls(values=theta, std=std, free=free, identifiable=ident, x=x, x_names=list(nlp.x_names),
                   corr=corr, success=bool(info.get("success")), status=str(info.get("status")),
                   iterations=int(info.get("iterations", -1)), solver=solver, timings=timings,
                   cost=float(info.get("cost", np.nan)), sigma=float(nlp.sigma), ids=ids,
                   visible=visible, names=list(m.names), normals=np.asarray(theta["normal"]).copy(), glossy=m.glossy.copy(), info=dict(info),
                   warm_start=warm_start, flags=flags, extra=extra)

    # ------------------------------------------------------------------ views
    def reported(self, name: str) -> np.ndarray:
        """Values with unidentifiable entries replaced by NaN (what may be quoted as a result)."""
        v = np.array(self.values[name], float)
        bad = ~self.identifiable[name]
        v[bad] = np.nan
        return v

    def summary(self) -> str:
        head = "OK" if self.success else "FAILED"
        return (f"{head}: {self.solver} status '{self.status}', {self.iterations} iterations, "
                f"cost {self.cost:.6g}, solve {self.timings.get('solve_s', 0):.3f} s")

    def to_json_dict(self, geometry=None) -> dict:
        """estimate.json (DESIGN.md section 5); merged into ``geometry.to_json_dict()`` if given.

        Each patch gets its BRDF parameters by name with ``<name>_std``; unidentifiable values
        are null with an ``unidentifiable`` list; a refined hidden position replaces the
        geometry stage's, with ``position_std``. The stage entry ``reflectance`` holds status,
        iterations and wall time.
        """
        from ..geometry.result import _jsonable

        geometry = geometry if geometry is not None else self.extra.get("geometry_estimate")
        base = geometry.to_json_dict() if geometry is not None else {"patches": []}
        by_id = {int(p["id"]): p for p in base.get("patches", [])}
        out_patches = []
        for k in range(len(self.ids)):
            pid = int(self.ids[k])
            p = dict(by_id.get(pid, {"id": pid, "visible": bool(self.visible[k]),
                                     "position": self.values["position"][k].tolist(),
                                     "normal": self.normals[k].tolist()}))
            unid = []
            for n in _BRDF_NAMES:
                if n != "albedo" and not self.glossy[k]:
                    continue
                ok = self.identifiable[n][k]
                p[n] = float(self.values[n][k]) if ok else None
                s = self.std[n][k]
                p[f"{n}_std"] = float(s) if (ok and np.isfinite(s)) else None
                if not ok:
                    unid.append(n)
            if self.free["position"][k]:
                ok = self.identifiable["position"][k]
                p["position"] = self.values["position"][k].tolist() if ok else None
                p["position_std"] = self.std["position"][k].tolist() if ok else None
                if not ok:
                    unid.append("position")
            ns = self.extra.get("normal_source", {}).get(pid)
            if ns is not None:
                p["normal_source"] = ns
            if self.free.get("normal", np.zeros(len(self.ids), bool))[k]:
                ok = self.identifiable["normal"][k]
                p["normal"] = self.values["normal"][k].tolist() if ok else None
                sn = self.std["normal"][k]
                p["normal_std"] = sn.tolist() if (ok and np.all(np.isfinite(sn))) else None
                if not ok:
                    unid.append("normal")
            elif ns is not None and ns.startswith("assumed"):
                p["normal"] = self.normals[k].tolist()
            why = self.extra.get("degenerate_hidden", {}).get(pid)
            if why is not None:
                p["ambiguous"] = why
                unid.append("position")
            if unid:
                p["unidentifiable"] = unid
            out_patches.append(p)
        base["patches"] = out_patches
        stages = base.setdefault("stages", {})
        stages["reflectance"] = {"status": self.status, "success": self.success, "solver": self.solver,
                                 "iterations": self.iterations,
                                 "wall_time_s": float(sum(self.timings.values())),
                                 "cost": self.cost, "flags": self.flags,
                                 **{k: v for k, v in self.extra.items() if k != "geometry_estimate"}}
        base["success"] = bool(base.get("success", True)) and self.success
        return _jsonable(base)
