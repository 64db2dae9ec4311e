"""Relighting from the estimate: new lit patches, a new source, a new viewpoint, with std.

When to use
-----------
When the measured STIR cannot answer (patches it never lit, a source or camera somewhere else, a
different material): the estimate (``SceneBelief``) is rendered by the project's forward model
``stircasadi.transport.simulate`` with the bounce order the scene needs (or ``"all"``), and every
rendered value carries the standard deviation propagated from the estimate's covariance.

Equations
---------
* transient: ``simulate(scene_at(theta), grid, sensor, bounces)`` -> ``stir[i, j, k]``; under an
  ``Illumination`` it is superposed as in ``stircasadi.apps.relight``;
* steady state, every bounce: ``R = O0 (I - T0)^{-1} S0`` (the delay network at zero frequency,
  ``TransportSystem.steady_matrices``), the time integral of the all-bounce STIR;
* uncertainty, linearised: ``Var f = diag(J Sigma J^T)`` with ``J`` the central finite difference
  of the renderer over the parameter vector (step ``rel_step`` x each parameter's std), checked
  against a Monte Carlo over parameter draws (``monte_carlo``; tests/test_apps_render.py).

What it neglects: the estimate's error beyond its (Gaussian) covariance; parameters reported
without a std (``missing_std`` in the result: their uncertainty is not in the std, which is then
a lower bound); visibility flips inside the finite-difference step (a patch seen at grazing).
A grid chooser from the network's arrival window (``auto_grid``) lives here until it moves to
``stircasadi.transport``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import EstimateInputError, TimeGridError
from ..sensor import Sensor
from ..timegrid import TimeGrid
from ..transport import TransportSystem, needed_bounces, path_sum, simulate
from ..transport.deposit import kernel_support
from .belief import SceneBelief, _psd_factor
from .relight import Illumination, superpose

__all__ = ["RenderSettings", "Rendering", "render", "auto_grid", "steady_state", "monte_carlo"]


@dataclass
class RenderSettings:
    """How an estimate is rendered and its uncertainty propagated."""

    #: bounce order of the transient: None = what the scene needs (3 with hidden patches, else
    #: 2), an integer K, or "all" (frequency-domain resolvent; needs a Gaussian response)
    bounces: int | str | None = None
    #: bin width (m of path) of the grid chosen when none is given
    bin_width: float = 0.005
    #: empty bins kept before the first and after the last arrival of an automatic grid
    margin_bins: int = 16
    #: finite-difference step of each parameter, as a fraction of its std
    rel_step: float = 0.05
    #: propagate the std (False: values only, one render)
    with_std: bool = True

    def validate(self) -> "RenderSettings":
        if not (self.bounces is None or self.bounces == "all" or
                (isinstance(self.bounces, int) and not isinstance(self.bounces, bool) and self.bounces >= 1)):
            raise EstimateInputError(f"bounces must be None, 'all' or an integer >= 1; got {self.bounces!r}.")
        if not (self.bin_width > 0 and math.isfinite(self.bin_width)):
            raise TimeGridError(f"bin_width must be > 0 metres of path; got {self.bin_width!r}.")
        if not (isinstance(self.margin_bins, int) and self.margin_bins >= 0):
            raise EstimateInputError(f"margin_bins must be an integer >= 0; got {self.margin_bins!r}.")
        if not (0 < self.rel_step <= 1):
            raise EstimateInputError(f"rel_step must be in (0, 1]; got {self.rel_step!r}.")
        return self


@dataclass
class Rendering:
    """A render of the estimate (ids are the estimate's patch ids).

    ``stir`` (n_ill, n_obs, n_bins) and ``steady`` (n_ill, n_obs, every bounce); under an
    illumination ``relit`` (n_obs, n_bins) and ``relit_steady`` (n_obs,). Each ``*_std`` is the
    propagated one-sigma std (None when not propagated).
    """

    stir: np.ndarray
    steady: np.ndarray
    grid: TimeGrid
    ill_ids: np.ndarray
    obs_ids: np.ndarray
    stir_std: np.ndarray | None = None
    steady_std: np.ndarray | None = None
    relit: np.ndarray | None = None
    relit_steady: np.ndarray | None = None
    relit_std: np.ndarray | None = None
    relit_steady_std: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)


def auto_grid(scene, bin_width: float, sensor: Sensor | None = None, bounces: int | None = None,
              margin_bins: int = 16, legs_included: bool = True) -> TimeGrid:
    """A grid holding every path of up to ``bounces`` bounces (default: what the scene needs),
    with ``margin_bins`` empty bins on each side, starting on a whole number of bins."""
    sensor = sensor or Sensor()
    K = needed_bounces(scene) if bounces is None else int(bounces)
    system = TransportSystem.build(scene, legs_included=legs_included)
    lo, hi = system.arrival_window(K)
    if not np.isfinite(lo):
        raise EstimateInputError("No light path reaches the camera in this configuration (no patch is "
                                 "both reachable by the source and seen by the camera).")
    s_lo, s_hi = kernel_support(sensor.irf, bin_width, False)
    k0 = int(math.floor((lo + s_lo) / bin_width)) - margin_bins
    k1 = int(math.ceil((hi + s_hi) / bin_width)) + margin_bins
    return TimeGrid(k0 * bin_width, bin_width, max(k1 - k0, 1))


def steady_state(scene) -> np.ndarray:
    """All-bounce time-integrated STIR (n_ill, n_obs): ``O0 (I - T0)^{-1} S0``."""
    return _steady(TransportSystem.build(scene))


def _steady(system) -> np.ndarray:
    """``O0 (I - T0)^{-1} S0`` of a built network (dense for small networks, sparse else)."""
    N, ni, no = system.n_nodes, system.n_ill, system.n_obs
    if ni == 0 or no == 0:
        return np.zeros((ni, no))
    if N > 1500:
        from scipy.sparse import identity
        from scipy.sparse.linalg import spsolve

        S0, T0, O0 = system.steady_matrices()
        X = np.asarray(spsolve(identity(N, format="csc") - T0.tocsc(), S0.toarray())).reshape(N, ni)
        return np.asarray(O0 @ X).T

    def dense(terms, shape):
        r, c, v, _ = terms
        m = np.zeros(shape)
        np.add.at(m, (r, c), v)
        return m
    S0, T0, O0 = dense(system.S, (N, ni)), dense(system.T, (N, N)), dense(system.O, (no, N))
    return (O0 @ np.linalg.solve(np.eye(N) - T0, S0)).T


class _Renderer:
    """theta -> rendered outputs on the nominal configuration's ids and grid."""

    def __init__(self, belief: SceneBelief, grid, sensor, source, camera, illumination, settings,
                 brdf_override, legs_included):
        self.b, self.sensor, self.settings = belief, sensor or Sensor(), settings
        self.source, self.camera, self.brdf_override = source, camera, brdf_override
        self.illumination, self.legs = illumination, legs_included
        scene = belief.scene_at(belief.values, source=source, camera=camera, brdf_override=brdf_override)
        self.scene = scene
        self.ill_ids = belief.ids[scene.illuminated_ids]
        self.obs_ids = belief.ids[scene.observed_ids]
        lit = None
        if illumination is not None:
            lit = (illumination.ids if illumination.ids is not None else self.ill_ids)
        belief.check_renderable(scene, lit)
        if len(self.ill_ids) == 0 or len(self.obs_ids) == 0:
            raise EstimateInputError(
                f"In this configuration (source {np.round(scene.source, 4).tolist()}, camera "
                f"{np.round(scene.camera, 4).tolist()}) {len(self.ill_ids)} patches can be lit and "
                f"{len(self.obs_ids)} are seen; nothing to render. Move the source or camera in front "
                "of the patches (their normals point toward the side they can be lit and seen from).")
        b = settings.bounces
        self.K = "all" if b == "all" else (needed_bounces(scene) if b is None else int(b))
        if grid is None:
            grid = auto_grid(scene, settings.bin_width, self.sensor,
                             None if self.K == "all" else self.K, settings.margin_bins, legs_included)
        self.grid = grid
        self.method = "frequency" if self.K == "all" else "auto"

    def __call__(self, theta, nominal: bool = False) -> dict:
        scene = self.b.scene_at(theta, source=self.source, camera=self.camera,
                                brdf_override=self.brdf_override)
        system = TransportSystem.build(scene, legs_included=self.legs)
        meta = None
        if nominal or self.K == "all":
            tr = simulate(scene, self.grid, sensor=self.sensor, bounces=self.K, method=self.method,
                          legs_included=self.legs, allow_truncation=not nominal)
            meta, t_stir = tr.metadata, tr.stir
        else:  # the same path sums simulate() runs, without its grid checks and energy report
            t_stir = path_sum(system, self.grid, self.sensor.irf, self.K)
        tr = _Tr(t_stir, system.ill_ids, system.obs_ids)
        ids_i, ids_j = self.b.ids[tr.ill_ids], self.b.ids[tr.obs_ids]
        ri = _place(self.ill_ids, ids_i)
        rj = _place(self.obs_ids, ids_j)
        stir = np.zeros((len(self.ill_ids), len(self.obs_ids), self.grid.n_bins))
        stir[np.ix_(ri[0], rj[0])] = tr.stir[np.ix_(ri[1], rj[1])]
        st = _steady(system)
        steady = np.zeros((len(self.ill_ids), len(self.obs_ids)))
        steady[np.ix_(ri[0], rj[0])] = st[np.ix_(ri[1], rj[1])]
        out = {"stir": stir, "steady": steady}
        if self.illumination is not None:
            r = superpose(stir, self.grid, self.ill_ids, self.obs_ids, self.illumination,
                          irf=self.sensor.irf)
            rows, w, _, p = self.illumination.resolve(self.ill_ids)
            out["relit"] = r.transient
            out["relit_steady"] = np.einsum("i,ij->j", w * p.sum(axis=1), steady[rows])
        if nominal:
            out["_meta"] = meta
        return out


@dataclass
class _Tr:
    stir: np.ndarray
    ill_ids: np.ndarray
    obs_ids: np.ndarray


def _place(nominal_ids, ids):
    """Index pairs (into nominal, into ids) of the ids present in both."""
    pos = {int(v): k for k, v in enumerate(ids)}
    a = [k for k, v in enumerate(nominal_ids) if int(v) in pos]
    return np.array(a, int), np.array([pos[int(nominal_ids[k])] for k in a], int)


def render(belief: SceneBelief, grid: TimeGrid | None = None, sensor: Sensor | None = None,
           source=None, camera=None, illumination: Illumination | None = None,
           settings: RenderSettings | None = None, brdf_override: dict | None = None,
           legs_included: bool = True) -> Rendering:
    """Render the estimate (module doc) and propagate its covariance to every value.

    Parameters
    ----------
    belief : the estimate (``SceneBelief.from_estimate``).
    grid : time axis (default: ``auto_grid`` for the configuration).
    sensor : impulse response of the render (default ideal; use the capture's for comparisons).
    source, camera : new positions in the estimate's frame (default: the estimate's).
    illumination : an ``Illumination`` over the patches the source can reach in this
        configuration (ids = estimate ids), or None for the STIR only.
    brdf_override : ``{patch id: BRDF}`` (material replacement, ``stircasadi.apps.replace``).
    """
    settings = (settings or RenderSettings()).validate()
    rd = _Renderer(belief, grid, sensor, source, camera, illumination, settings, brdf_override,
                   legs_included)
    nom = rd(belief.values, nominal=True)
    meta = {"verdict": belief.verdict, "bounces": rd.K, "source": rd.scene.source.tolist(),
            "camera": rd.scene.camera.tolist(), "simulation": {k: v for k, v in nom.pop("_meta").items()
                                                              if isinstance(v, (int, float, str, bool))},
            "steady_bounces": "all", "missing_std": list(belief.missing_std),
            "std_complete": not belief.missing_std, "n_params": belief.n_params}
    res = Rendering(nom["stir"], nom["steady"], rd.grid, rd.ill_ids, rd.obs_ids,
                    relit=nom.get("relit"), relit_steady=nom.get("relit_steady"), metadata=meta)
    if settings.with_std:
        std, n_eval = _fd_std(rd, belief, settings.rel_step, nom)
        res.stir_std, res.steady_std = std["stir"], std["steady"]
        res.relit_std, res.relit_steady_std = std.get("relit"), std.get("relit_steady")
        meta.update({"std_method": "linearised (central finite differences over the parameters)",
                     "n_renders": n_eval + 1})
    return res


def _fd_std(rd: _Renderer, belief: SceneBelief, rel_step: float, nom: dict) -> tuple[dict, int]:
    """std of every output from central differences: diag(J Sigma J^T) = rowsum((J L)^2)."""
    keys = list(nom)
    sig = belief.std
    active = np.flatnonzero(sig > 0)
    L = _psd_factor(belief.covariance)
    JL = np.zeros((sum(nom[k].size for k in keys), L.shape[1]))
    for p in active:
        h = rel_step * sig[p]
        tp, tm = belief.values.copy(), belief.values.copy()
        tp[p] += h
        tm[p] -= h
        fp, fm = rd(tp), rd(tm)
        col = np.concatenate([((fp[k] - fm[k]) / (2 * h)).ravel() for k in keys])
        JL += col[:, None] * L[p][None, :]
    out, o = {}, 0
    for k in keys:
        n = nom[k].size
        out[k] = np.sqrt(np.sum(JL[o:o + n] ** 2, axis=1)).reshape(nom[k].shape)
        o += n
    return out, 2 * len(active)


def monte_carlo(belief: SceneBelief, n_draws: int, rng: np.random.Generator, **render_kw) -> dict:
    """Sample std of every rendered output over ``n_draws`` parameter draws from the belief
    (the check of the linearised std); ``render_kw`` as for ``render`` (grid required)."""
    if render_kw.get("grid") is None:
        raise EstimateInputError("monte_carlo needs the grid of the render it checks (grid=...).")
    settings = (render_kw.pop("settings", None) or RenderSettings()).validate()
    rd = _Renderer(belief, render_kw.pop("grid"), render_kw.pop("sensor", None),
                   render_kw.pop("source", None), render_kw.pop("camera", None),
                   render_kw.pop("illumination", None), settings,
                   render_kw.pop("brdf_override", None), render_kw.pop("legs_included", True))
    if render_kw:
        raise EstimateInputError(f"monte_carlo: unknown arguments {sorted(render_kw)}.")
    draws = belief.draw(rng, n_draws)
    acc = None
    for th in draws:
        f = rd(th)
        if acc is None:
            acc = {k: [] for k in f}
        for k, v in f.items():
            acc[k].append(v)
    return {k: np.std(np.array(v), axis=0, ddof=1) for k, v in acc.items()}
