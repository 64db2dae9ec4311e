"""``TransientModel``: the symbolic STIR of a patch scene in CasADi — declare, ``setup()``, solve.

When to use
-----------
Build it from a ``Scene`` (twin experiments) or from arrays (an estimate's geometry), declare
which quantities are unknown (bounds, scales, initial values; positions in a basis: a camera
ray, a plane, free 3-D), which patches are extended discs, whose albedo unknown is the product
albedo x area, which areas are a calibrated pixel's footprint; call ``setup()``; hand it to a
solver (``stircasadi.joint``). The model describes; it never solves (STYLE.md rules 1, 2).

Equation
--------
The transient rendering equation of ``stircasadi.transport`` expanded into paths of 1..K
bounces (``model/output.py``: amplitude, delay, bin integral — the numeric transport's formulas,
mirrors included); vertices and their geometry in ``model/vertices.py``; paths and windows in
``model/paths.py``; the unknown registry in ``model/parameters.py``; the energy terms in
``model/energy.py``.

What it neglects
----------------
Everything the forward model neglects, bounces beyond K, and changes of visibility as unknowns
move (legs and mirror hits are decided at the initial geometry). A hidden point patch's albedo
and area enter third bounces only as their product; an extended patch's size shows in the
spread of its returns.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from ..brdf import Lambertian, Mirror, Phong
from ..errors import ModelError
from ..radiometry import facing_matrix, perpendicular
from ..timegrid import TimeGrid
from .output import OutputStructure, build_output, numeric_stir, path_terms
from .parameters import ParameterSet
from .paths import enumerate_paths, general_triples, legs_between, windows
from .energy import flux_column_sums
from .vertices import VertexLayout, patch_quantities, vertex_quantities

__all__ = ["TransientModel", "ModelInfo"]


@dataclass
class ModelInfo:
    """Size and cost of a built model (for benchmarks and reports)."""

    n_paths: int = 0
    n_variable_paths: int = 0
    n_support: int = 0
    n_unknowns: int = 0
    n_vertices: int = 0
    build_time_s: float = 0.0
    bounces: int = 0
    extra: dict = field(default_factory=dict)


class TransientModel:
    """Symbolic STIR model of a patch scene: declare unknowns, ``setup()``, then solve.

    Parameters
    ----------
    positions, normals : (M, 3) metres / unit vectors (initial values or fixed).
    areas : (M,) m^2.
    grid : TimeGrid of the data. irf : impulse response (``stircasadi.irf``; GaussianIRF for
        moving vertices).
    ill_ids, obs_ids : patch indices of the STIR rows (pulse) and columns (camera).
    brdfs : M Lambertian / Phong / Mirror objects (kinds and initial values).
    source, camera : (3,) points. ``phi``: pulse energy. ``legs_included``: as in Capture.
    visibility : (M, M) bool patch-to-patch visibility (default: the facing test).
    bounces : K, the largest bounce order modelled (>= 1).
    bounces_hidden : the largest order of paths through a hidden patch (neither illuminated nor
        observed); default K.
    """

    def __init__(self, positions, normals, areas, grid: TimeGrid, irf, ill_ids, obs_ids, brdfs,
                 source=(0.0, 0.0, 0.0), camera=None, phi: float = 1.0, legs_included: bool = True,
                 visibility=None, bounces: int = 2, names=None, bounces_hidden: int | None = None):
        z = np.asarray(positions, float)
        n = np.asarray(normals, float)
        a = np.asarray(areas, float)
        M = len(z)
        if M < 1 or z.shape != (M, 3) or n.shape != (M, 3) or a.shape != (M,):
            raise ModelError(f"positions and normals must be (M, 3) and areas (M,) with M >= 1; got "
                             f"{z.shape}, {n.shape}, {a.shape}.")
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(n)) and np.all(a > 0)):
            raise ModelError("positions/normals must be finite and areas > 0 m^2.")
        if not isinstance(grid, TimeGrid):
            raise ModelError(f"grid must be a TimeGrid; got {type(grid).__name__}.")
        if not (isinstance(bounces, (int, np.integer)) and bounces >= 1):
            raise ModelError(f"bounces must be an integer >= 1; got {bounces!r}.")
        brdfs = list(brdfs)
        if len(brdfs) != M:
            raise ModelError(f"brdfs must give one BRDF per patch ({M}); got {len(brdfs)}.")
        for k, b in enumerate(brdfs):
            if not isinstance(b, (Lambertian, Phong, Mirror)):
                raise ModelError(f"Patch {k} has a {type(b).__name__}; use Lambertian, Phong or Mirror.")
        self.M = M
        self.z0 = z.copy()
        self.normals = n / np.linalg.norm(n, axis=1)[:, None]
        self.grid, self.irf = grid, irf
        self.ill_ids = np.asarray(ill_ids, int)
        self.obs_ids = np.asarray(obs_ids, int)
        self.source = np.asarray(source, float)
        self.camera = self.source.copy() if camera is None else np.asarray(camera, float)
        self.phi = float(phi)
        self.legs_included = bool(legs_included)
        self.bounces = int(bounces)
        self.bounces_hidden = None if bounces_hidden is None else int(bounces_hidden)
        self.names = list(names) if names is not None else [f"P{k}" for k in range(M)]
        self.glossy = np.array([isinstance(b, Phong) for b in brdfs])
        self.mirrors = {k: b for k, b in enumerate(brdfs) if isinstance(b, Mirror)}
        self.is_mirror = np.array([k in self.mirrors for k in range(M)])
        vis = facing_matrix(z, self.normals) if visibility is None else np.asarray(visibility, bool)
        if vis.shape != (M, M):
            raise ModelError(f"visibility must be ({M}, {M}); got {vis.shape}.")
        self.visibility = vis & ~self.is_mirror[:, None] & ~self.is_mirror[None, :]
        self.params = ParameterSet(M, {
            "albedo": np.array([b.diffuse_albedo for b in brdfs], float),
            "area": a.copy(), "position": z.copy(),
            "specular": np.array([getattr(b, "specular", 0.0) for b in brdfs], float),
            "exponent": np.array([getattr(b, "exponent", 0.0) for b in brdfs], float),
            "tilt": np.zeros(M), "tilt2": np.zeros(M)})
        self.tilt_axis = np.array([perpendicular(v) for v in self.normals])
        self.frame_ref = np.array([perpendicular(v) for v in self.normals])
        self.albedo_product = np.zeros(M, bool)
        self.footprint = np.full(M, np.nan)
        self.general = np.zeros(M, bool)
        self.triples = np.zeros((0, 3), int)
        self.general_bounds = (0.0, 10.0 / math.pi, 1.0 / math.pi)
        self.extended: dict[int, tuple[int, int]] = {}
        self.gain_free = False
        self._gain_bounds = (1e-12, 1e12)
        self._locked = False
        self.info = ModelInfo(bounces=self.bounces)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_scene(cls, scene, grid: TimeGrid, irf, bounces: int | None = None,
                   legs_included: bool = True) -> "TransientModel":
        """A model with the scene's geometry and BRDFs as fixed values (declare unknowns next)."""
        from ..transport import needed_bounces

        K = needed_bounces(scene) if bounces is None else bounces
        return cls(scene.positions, scene.normals, scene.areas, grid, irf, scene.illuminated_ids,
                   scene.observed_ids, scene.brdfs, source=scene.source, camera=scene.camera,
                   phi=scene.phi, legs_included=legs_included, visibility=scene.patch_visibility,
                   bounces=K, names=[p.name or f"P{k}" for k, p in enumerate(scene.patches)])

    # ------------------------------------------------------------------ declaration
    def _check_open(self, what: str):
        if self._locked:
            raise ModelError(f"The model is set up and locked; {what} must come before setup(). "
                             "Build a new TransientModel to change its unknowns.")

    def _select(self, patches) -> np.ndarray:
        if patches is None:
            return np.arange(self.M)
        if isinstance(patches, str):
            table = {"all": np.ones(self.M, bool), "glossy": self.glossy.copy()}
            if patches not in table:
                raise ModelError(f"patches must be indices, a bool mask, 'all' or 'glossy'; got {patches!r}.")
            return np.flatnonzero(table[patches])
        p = np.asarray(patches)
        if p.dtype == bool:
            if p.shape != (self.M,):
                raise ModelError(f"A patch mask must have shape ({self.M},); got {p.shape}.")
            return np.flatnonzero(p)
        p = p.astype(int).ravel()
        if p.size and (p.min() < 0 or p.max() >= self.M):
            raise ModelError(f"patch indices must lie in 0..{self.M - 1}; got {p.tolist()}.")
        return p

    def set_unknown(self, name: str, patches=None, lower=None, upper=None, scale=None,
                    initial=None, basis=None) -> "TransientModel":
        """Declare ``name`` unknown on ``patches`` (indices, mask, 'all', 'glossy').

        BRDF parameters and areas: ``theta = scale * x`` within [lower, upper]. Positions:
        ``z = z0 + basis (scale * x)`` with ``basis`` (3, d) or (k, 3, d) (d = 1: along a
        camera ray; 2: in a plane; default 3: free) and lower/upper the offsets allowed along
        each basis direction (metres; finite, they set the model's time windows)."""
        self._check_open("set_unknown")
        self.params[name]  # unknown names raise here, naming the allowed ones
        sel = self._select(patches)
        if np.any(self.is_mirror[sel]):
            raise ModelError(f"Patches {sel[self.is_mirror[sel]].tolist()} are mirrors: they have no "
                             "unknowns in the model (their geometry is fixed).")
        if name in ("specular", "exponent") and np.any(~self.glossy[sel]):
            raise ModelError(f"'{name}' is a Phong parameter; patches {sel[~self.glossy[sel]].tolist()} "
                             "are Lambertian. Give them a Phong BRDF (specular=0 is fine) or "
                             "select patches='glossy'.")
        if name == "albedo" and np.any(self.general[sel]):
            raise ModelError("A general-BRDF patch has no albedo unknown (its f_kij are the unknowns).")
        self.params.declare(name, sel, lower, upper, scale, initial, basis)
        return self

    def set_tilt_axes(self, patches, axis) -> "TransientModel":
        """Rotation axes of the normal unknowns ``tilt`` / ``tilt2`` on ``patches`` (projected
        perpendicular to each initial normal; flatland: the plane's normal)."""
        self._check_open("set_tilt_axes")
        sel = self._select(patches)
        ax = np.array(np.broadcast_to(np.asarray(axis, float), (len(sel), 3)))
        for i, k in enumerate(sel):
            v = ax[i] - np.dot(ax[i], self.normals[k]) * self.normals[k]
            nv = np.linalg.norm(v)
            if not np.isfinite(nv) or nv < 1e-6 * max(np.linalg.norm(ax[i]), 1e-300):
                raise ModelError(f"The tilt axis {ax[i].tolist()} of patch {k} ({self.names[k]}) is "
                                 f"parallel to its normal {self.normals[k].tolist()} (or not finite): a "
                                 "rotation about it leaves the normal unchanged. Give an axis "
                                 "perpendicular to the normal (flatland: the plane's normal).")
            self.tilt_axis[k] = v / nv
        return self

    def set_extended(self, patches, rings: int = 2, per_ring: int = 6) -> "TransientModel":
        """Model ``patches`` as discs of their area (``rings`` x ``per_ring`` quadrature points),
        so their size shows in the spread of their returns (declare 'area' unknown to fit it)."""
        self._check_open("set_extended")
        for k in self._select(patches):
            if int(k) in self.ill_ids or int(k) in self.obs_ids:
                raise ModelError(f"Patch {k} is illuminated or observed: only hidden patches can be "
                                 "extended (a visible patch is a pixel's footprint).")
            self.extended[int(k)] = (int(rings), int(per_ring))
        return self

    def set_albedo_product(self, patches) -> "TransientModel":
        """The albedo unknown of ``patches`` is albedo x area (m^2): what third bounces through an
        unresolved hidden patch identify. Its bounds default to [0, 1 m^2]."""
        self._check_open("set_albedo_product")
        sel = self._select(patches)
        self.albedo_product[sel] = True
        P = self.params["albedo"]
        P.value[sel] = P.value[sel] * self.params["area"].value[sel]
        P.upper[sel] = 1.0
        P.scale[sel] = 1e-3
        return self

    def set_footprint(self, patches, solid_angle) -> "TransientModel":
        """Areas of ``patches`` are their calibrated pixels' footprints: Omega r^2 / cos(theta)."""
        self._check_open("set_footprint")
        sel = self._select(patches)
        om = np.broadcast_to(np.asarray(solid_angle, float), (len(sel),))
        if not np.all(om > 0):
            raise ModelError(f"pixel solid angles must be > 0 sr; got {om.tolist()}.")
        self.footprint[sel] = om
        return self

    def set_general_brdf(self, patches, upper: float = 10.0 / math.pi,
                         scale: float = 1.0 / math.pi) -> "TransientModel":
        """Give ``patches`` a general, tabulated BRDF: one unknown f_kij per (k, i, j) met on a
        path (the paper's general form-factor model; -1 the source, -2 the camera). The NLP adds
        Helmholtz reciprocity and energy conservation over them as constraints."""
        self._check_open("set_general_brdf")
        sel = self._select(patches)
        if np.any(self.glossy[sel]):
            raise ModelError("A patch with a Phong BRDF cannot also be general; pick Lambertian patches.")
        if np.any(self.params["albedo"].free[sel]):
            raise ModelError("A general-BRDF patch has no albedo unknown (its f_kij are the unknowns); "
                             "declare set_unknown('albedo', ...) on the other patches only.")
        self.general[sel] = True
        self.general_bounds = (0.0, float(upper), float(scale))
        return self

    def set_unknown_gain(self, initial: float = 1.0, lower: float = 1e-12, upper: float = 1e12) -> "TransientModel":
        """Make the pulse energy x detector gain ``phi`` (the STIR's unit: counts, volts...) one
        more unknown (scaled by its initial value). A simulated STIR in radiance units has phi = 1."""
        self._check_open("set_unknown_gain")
        if not (0 < lower <= initial <= upper):
            raise ModelError(f"gain bounds must satisfy 0 < lower <= initial <= upper; got {lower}, "
                             f"{initial}, {upper}.")
        self.phi = float(initial)
        self.gain_free = True
        self._gain_bounds = (float(lower), float(upper))
        return self

    def fix(self, name: str, values, patches=None) -> "TransientModel":
        """Fix ``name`` to ``values`` on ``patches`` (no longer unknown there)."""
        self._check_open("fix")
        self.params.fix(name, self._select(patches), values)
        return self

    # ------------------------------------------------------------------ setup
    def setup(self, symbolic: bool = True) -> "TransientModel":
        """Check the declaration, enumerate paths, build the CasADi graph and lock the model.
        ``symbolic=False``: paths and windows only, no graph; ``simulate`` then sums the paths
        in NumPy (a probe model: no NLP can be built on it)."""
        self._check_open("setup")
        t0 = time.perf_counter()
        pr = self.params
        pr.lock(self.names)
        self.layout = VertexLayout.build(self.M, self.extended)
        moving_patch = pr["position"].free.copy()
        for k in self.extended:
            moving_patch[k] |= pr["area"].free[k] | pr["tilt"].free[k] | pr["tilt2"].free[k]
        if moving_patch.any() and not getattr(self.irf, "differentiable", False):
            raise ModelError("Moving vertices (unknown positions, extended patches) need a "
                             "differentiable delay kernel: a Gaussian or measured impulse response; "
                             f"got {self.irf.describe()}. Fix the positions or give the capture's IRF.")
        # the general BRDF's unknowns are indexed by the (prev, patch, next) triples of the paths
        self.legs = legs_between(self.layout, self.visibility, self.mirrors, pr["position"].value,
                                 self.normals, pr["area"].value)
        ill_vertex = self.layout.first[self.ill_ids]
        obs_col = -np.ones(self.layout.n, int)
        for c, k in enumerate(self.obs_ids):
            if not self.is_mirror[k]:
                obs_col[self.layout.first[k]] = c
        ill_ok = ~self.is_mirror[self.ill_ids]
        rows = np.flatnonzero(ill_ok)
        hid = np.ones(self.M, bool)
        hid[self.ill_ids] = False
        hid[self.obs_ids] = False
        paths = enumerate_paths(self.legs, ill_vertex[rows], obs_col, len(self.obs_ids),
                                self.bounces, moving_patch[self.layout.patch], hid[self.layout.patch],
                                self.bounces_hidden)
        for g in paths:  # enumerate_paths numbered the rows of ill_ok; map back to STIR rows
            r, c = np.divmod(g.trace, len(self.obs_ids))
            g.trace = rows[r] * len(self.obs_ids) + c
        self.paths = paths
        if self.general.any():
            self.triples = general_triples(self.paths, self.layout.patch, self.general)
            if not len(self.triples):
                raise ModelError("The general-BRDF patches lie on no path of the model.")
        if pr.n_x == 0 and not self.general.any():
            raise ModelError("No unknowns declared: call set_unknown('albedo', ...) (or 'area', "
                             "'specular', 'exponent', 'position', 'tilt') before setup().")
        n_f = len(self.triples)
        n_g = int(self.gain_free)
        lo_, hi_, sc_ = self.general_bounds
        self.x = ca.MX.sym("x", pr.n_x + n_f + n_g)
        xs, xf = self.x[:pr.n_x], self.x[pr.n_x:pr.n_x + n_f]
        f0 = np.array([self._patch_albedo0(i) / math.pi for _, i, _ in self.triples]) if n_f else np.zeros(0)
        self.fkij_scale = sc_
        self.gain_scale = self.phi
        g_lo, g_hi = self._gain_bounds
        # the gain enters as phi0 exp(x_g): its valley with the albedos (gain x albedo^2 fixed)
        # is then a straight line
        self.x0 = np.concatenate([pr.x0, f0 / sc_, [0.0] * n_g])
        self.lbx = np.concatenate([pr.lbx, np.full(n_f, lo_ / sc_), [np.log(g_lo / self.phi)] * n_g])
        self.ubx = np.concatenate([pr.ubx, np.full(n_f, hi_ / sc_), [np.log(g_hi / self.phi)] * n_g])
        self.x_names = pr.x_names + [self.triple_name(t) for t in range(n_f)] + ["log_gain"] * n_g
        self.n_x = pr.n_x + n_f + n_g
        self.phi_sym = ca.exp(self.x[self.n_x - 1]) * self.phi if n_g else self.phi
        self.theta_sym = pr.theta_sym(xs)
        fk_sym = xf * sc_ if n_f else None
        self.vq_sym = vertex_quantities(patch_quantities(self.theta_sym, self), self.layout, self)
        vq0 = self._vq_num(self.x0)
        reach = self._reach()
        self.trace_lo, self.trace_hi, self.seg_start, self.support, self.support_trace = windows(
            self.paths, lambda g: path_terms(vq0, g.verts, g.via, self, f0)[1], reach[self.layout.patch],
            *self.irf.support(), self.grid, len(self.ill_ids) * len(self.obs_ids))
        self._locked = True
        self.info.n_paths = sum(len(g.verts) for g in self.paths)
        self.symbolic = symbolic
        if symbolic:
            self.output: OutputStructure = build_output(self, self.vq_sym, vq0, fk_sym, f0)
            self.y_sym = self.output.y
            self.f_y = ca.Function("stir_model", [self.x], [self.y_sym], ["x"], ["y"])
            self.info.n_variable_paths = self.output.n_variable_paths
        self.info.n_support = len(self.support)
        self.info.n_unknowns = self.n_x
        self.info.n_vertices = self.layout.n
        self.info.build_time_s = time.perf_counter() - t0
        return self

    def _patch_albedo0(self, k):
        return float(self.params["albedo"].value[k])

    def _reach(self) -> np.ndarray:
        """How far each patch's vertices can move within the bounds (metres)."""
        pr = self.params
        P = pr["position"]
        reach = np.zeros(self.M)
        for k in np.flatnonzero(P.free):
            d = int(pr.dims[k])
            ext = np.maximum(np.abs(P.lower[k, :d]), np.abs(P.upper[k, :d]))
            if not np.all(np.isfinite(ext)):
                raise ModelError(f"Patch {k} ({self.names[k]}): an unknown position needs finite bounds "
                                 "(offsets along its basis): pass lower=/upper= to set_unknown('position').")
            reach[k] = float(np.linalg.norm(ext))
        A = pr["area"]
        for k in self.extended:
            a_hi = A.upper[k] if A.free[k] else A.value[k]
            reach[k] += math.sqrt(a_hi / math.pi)
        return reach

    def _vq_num(self, x):
        x = np.asarray(x, float)
        th = self.params.theta(x[:self.params.n_x])
        vq = vertex_quantities(patch_quantities(th, self), self.layout, self)
        vq["phi"] = float(np.exp(x[-1]) * self.phi) if self.gain_free else self.phi
        return vq

    def triple_index(self, prev, i, nxt) -> np.ndarray:
        key = {tuple(t): n for n, t in enumerate(self.triples.tolist())}
        return np.array([key[(int(a), int(b), int(c))] for a, b, c in zip(prev, i, nxt)], int)

    def end_name(self, e) -> str:
        return {-1: "src", -2: "cam"}.get(int(e), self.names[int(e)] if e >= 0 else str(e))

    def triple_name(self, t) -> str:
        k, i, j = self.triples[t]
        return f"f[{self.end_name(k)},{self.names[i]},{self.end_name(j)}]"

    # ------------------------------------------------------------------ after setup
    def _require_setup(self, what: str):
        if not self._locked:
            raise ModelError(f"{what} needs a set-up model: call model.setup() first.")

    @property
    def is_setup(self) -> bool:
        return self._locked

    def param(self, name: str):
        return self.params[name]

    @property
    def blocks(self) -> list:
        """(name, patch, component) of each unknown of x (general f_kij next, as ('fkij', t, 0),
        the gain last, as ('gain', -1, 0))."""
        return (self.params.blocks + [("fkij", t, 0) for t in range(len(self.triples))]
                + [("gain", -1, 0)] * int(self.gain_free))

    @property
    def x_scale(self) -> np.ndarray:
        return np.concatenate([self.params.x_scale, np.full(len(self.triples), self.fkij_scale),
                               [1.0] * int(self.gain_free)])

    @property
    def tilt_free(self) -> np.ndarray:
        return self.params["tilt"].free | self.params["tilt2"].free

    def theta(self, x) -> dict:
        """Numeric values at x: albedo, area, specular, exponent, tilt, tilt2 (M,), position
        (M, 3), the unit ``normal`` (M, 3), the effective per-patch ``area_value`` (footprints
        applied) and, with a general BRDF, ``fkij``."""
        self._require_setup("theta()")
        x = np.asarray(x, float).ravel()
        th = self.params.theta(x[:self.params.n_x])
        pq = patch_quantities(th, self)
        th["normal"] = np.stack([np.asarray(c, float) for c in pq["n"]], axis=1)
        th["area_value"] = np.broadcast_to(np.asarray(pq["area"], float), (self.M,)).copy()
        if len(self.triples):
            th["fkij"] = x[self.params.n_x:self.params.n_x + len(self.triples)] * self.fkij_scale
        th["gain"] = float(np.exp(x[-1]) * self.gain_scale) if self.gain_free else self.phi
        return th

    def x_of(self, values: dict) -> np.ndarray:
        self._require_setup("x_of()")
        x = self.params.x_of(values)
        if len(self.triples):
            f = np.asarray(values.get("fkij", self.x0[self.params.n_x:self.params.n_x + len(self.triples)]
                                      * self.fkij_scale), float)
            x = np.concatenate([x, f / self.fkij_scale])
        if self.gain_free:
            x = np.concatenate([x, [np.log(float(values.get("gain", self.gain_scale)) / self.gain_scale)]])
        return x

    def rotated_normals(self, tilt, tilt2) -> np.ndarray:
        """Normals (M, 3) at tilt angles (radians, numeric)."""
        from .vertices import _rotated_normals

        return np.stack(_rotated_normals(self.normals, self.tilt_axis, np.asarray(tilt, float),
                                         np.asarray(tilt2, float)), axis=1)

    def evaluate(self, x=None) -> np.ndarray:
        """Model STIR on the support bins at scaled ``x`` (default: x0)."""
        self._require_setup("evaluate()")
        x = self.x0 if x is None else np.asarray(x, float)
        if not self.symbolic:
            return self.simulate(x).reshape(-1)[self.support]
        return np.asarray(self.f_y(x)).ravel()

    def simulate(self, x=None, numeric: bool = False) -> np.ndarray:
        """Full STIR (n_ill, n_obs, n_bins) at scaled ``x`` (default x0): zero off the support.
        ``numeric`` (always for a model set up with ``symbolic=False``): NumPy path sums."""
        self._require_setup("simulate()")
        x = self.x0 if x is None else np.asarray(x, float)
        shape = (len(self.ill_ids), len(self.obs_ids), self.grid.n_bins)
        if numeric or not self.symbolic:
            n_p = self.params.n_x
            fk = x[n_p:n_p + len(self.triples)] * self.fkij_scale if len(self.triples) else None
            return numeric_stir(self, self._vq_num(x), fk).reshape(shape)
        out = np.zeros(int(np.prod(shape)))
        out[self.support] = self.evaluate(x)
        return out.reshape(shape)

    def data_on_support(self, stir) -> np.ndarray:
        """The measured STIR restricted to the model's support bins."""
        self._require_setup("data_on_support()")
        stir = np.asarray(stir, float)
        want = (len(self.ill_ids), len(self.obs_ids), self.grid.n_bins)
        if stir.shape != want:
            raise ModelError(f"The data STIR has shape {stir.shape}; this model expects {want} "
                             "(n_illuminated, n_observed, n_bins).")
        return stir.reshape(-1)[self.support]

    def energy_terms(self):
        """Symbolic flux-transfer column sums (M,) for the energy constraint: see
        ``model.energy.flux_column_sums``."""
        self._require_setup("energy_terms()")
        return flux_column_sums(self)
