"""The symbolic transient model M(Theta, G) in CasADi: BRDF parameters and hidden geometry.

When to use
-----------
Build a ``TransientModel`` from a ``Scene`` (twin experiments) or from plain arrays / a
``GeometryEstimate`` (measurements), declare which quantities are unknown (with bounds, scales
and initial values) and which are fixed, call ``setup()``, and hand it to a solver in
``stircasadi.estimate``. The model describes; it never solves (STYLE.md rules 1, 2).

Equation implemented (bounce-limited path sums with exact, differentiable delays)
--------------------------------------------------------------------------------
The same transient rendering equation as ``stircasadi.transport.system``, expanded into light
paths of 1..K bounces. A path source -> u_1 -> ... -> u_n -> camera (u_1 illuminated, u_n
observed, consecutive vertices mutually visible) carries the amplitude

    a = (phi / a_{u_1}) * prod_m f_{u_m}(w_in, w_out) * prod_m G(u_m -> u_{m+1})

with f the patch BRDF (``stircasadi.brdf`` formulas, called with symbolic parameters) and G the
small-patch form factor (``stircasadi.radiometry.form_factor``), and arrives at

    tau = |s - z_{u_1}| + sum_m |z_{u_{m+1}} - z_{u_m}| + |z_{u_n} - o|

(the first and last legs only when ``legs_included``). It adds to bin k (left edge t_k)

    y_k += a * (H(t_k + w - tau) - H(t_k - tau)),     H = CDF of the impulse response,

exactly as ``stircasadi.transport.deposit`` does, so the output matches the numeric forward
model to rounding (about 1e-12 relative). For a Gaussian impulse response H is a normal CDF,
written with ``erf``: the delay is a smooth function of the geometry unknowns (no rounding).

Structure (why it stays buildable)
----------------------------------
Paths are enumerated once, numerically, at the initial geometry. A path whose vertices are all
fixed has a constant kernel: its contribution is ``A @ amp`` with a constant sparse matrix A
and a vector ``amp`` of symbolic amplitudes (polynomials in the BRDF parameters). Only paths
through a patch with unknown position get a symbolic kernel, evaluated elementwise on a
(paths x window) matrix and scattered by a constant 0/1 sparse matrix. The CasADi graph has a
fixed number of vectorised nodes whatever the scene size; memory grows with the number of paths
times the impulse-response window, and not at all with the number of bins outside the support.
The output is the STIR restricted to the bins where some path of the model deposits light
(``support``); elsewhere the model is exactly zero.

What it neglects
----------------
Everything the forward model neglects (small patches, no polarisation...), plus: bounces beyond
K; mirrors (a ``Mirror`` patch raises ``ModelError``); occlusion changes as hidden patches move
(visibility is computed once, at the initial geometry, also when normals rotate). Normals are
fixed unless declared unknown as rotations of the given normal n0 (``"tilt"``: angle a about a
per-patch axis ax perpendicular to n0, set with ``set_tilt_axes``; ``"tilt2"``: angle b toward
ax), n = cos b (cos a n0 + sin a ax x n0) + sin b ax. The albedo and the area of a hidden patch enter third bounces only as
the product ``albedo * area``: the model takes areas as known, and the albedo it recovers is
only as good as the area it is given.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from .brdf import Lambertian, Mirror, Phong
from .errors import ModelError
from .irf import bin_integral
from .radiometry import form_factor, source_irradiance
from .timegrid import TimeGrid

__all__ = ["TransientModel", "PARAMETERS"]

#: Unknowns a model can declare, with their default bounds, scale and per-patch shape.
PARAMETERS = {
    "albedo": {"lower": 0.0, "upper": 1.0, "scale": 1.0, "width": 1},
    "specular": {"lower": 0.0, "upper": 1.0, "scale": 1.0, "width": 1},
    "exponent": {"lower": 0.0, "upper": 500.0, "scale": 10.0, "width": 1},
    "position": {"lower": -np.inf, "upper": np.inf, "scale": 0.01, "width": 3},
    "distance": {"lower": 0.0, "upper": np.inf, "scale": 0.01, "width": 2},
    # normal rotations (radians): n = cos(b) (cos(a) n0 + sin(a) (ax x n0)) + sin(b) ax, with
    # a = tilt about the patch's tilt axis ax (perpendicular to n0) and b = tilt2 toward ax
    "tilt": {"lower": -math.radians(80.0), "upper": math.radians(80.0), "scale": 1.0, "width": 1},
    "tilt2": {"lower": -math.radians(80.0), "upper": math.radians(80.0), "scale": 1.0, "width": 1},
}



@dataclass
class _Param:
    name: str
    value: np.ndarray        # (M,) or (M, 3): fixed values and initial guesses
    free: np.ndarray         # (M,) bool: which patches carry this unknown
    lower: np.ndarray        # same shape as value
    upper: np.ndarray
    scale: np.ndarray        # theta = offset + scale * x
    offset: np.ndarray

    @property
    def width(self) -> int:
        return 1 if self.value.ndim == 1 else self.value.shape[1]


@dataclass
class Paths:
    """Light paths of one bounce order: vertex indices and the STIR trace each feeds."""

    verts: np.ndarray        # (P, n) patch indices
    trace: np.ndarray        # (P,) flat trace index row * n_obs + col
    variable: np.ndarray     # (P,) bool: some vertex has an unknown position


@dataclass
class ModelInfo:
    """Size and cost of a built model (for benchmarks and reports)."""

    n_paths: int = 0
    n_variable_paths: int = 0
    n_support: int = 0
    n_unknowns: int = 0
    build_time_s: float = 0.0
    bounces: int = 0
    extra: dict = field(default_factory=dict)


class TransientModel:
    """Symbolic STIR model of a patch scene: declare unknowns, ``setup()``, then solve.

    Parameters
    ----------
    positions, normals : (M, 3) arrays, metres / unit vectors.
    areas : (M,) m^2 (known; see the module docstring on albedo x area).
    grid : TimeGrid of the data.
    irf : impulse response object (``GaussianIRF`` for differentiable delays).
    ill_ids, obs_ids : patch indices of the STIR rows (pulse) and columns (camera).
    brdfs : sequence of M ``Lambertian`` / ``Phong`` objects giving kinds and initial values.
    source, camera : (3,) points. ``phi``: pulse energy. ``legs_included``: as in Capture.
    visibility : (M, M) bool patch-to-patch visibility (default: facing test at the given geometry).
    bounces : K, the largest bounce order modelled (>= 1).
    """

    def __init__(self, positions, normals, areas, grid: TimeGrid, irf, ill_ids, obs_ids, brdfs,
                 source=(0.0, 0.0, 0.0), camera=None, phi: float = 1.0, legs_included: bool = True,
                 visibility=None, bounces: int = 2, names=None):
        z = np.asarray(positions, float)
        n = np.asarray(normals, float)
        a = np.asarray(areas, float)
        M = len(z)
        if z.shape != (M, 3) or n.shape != (M, 3) or a.shape != (M,):
            raise ModelError(f"positions and normals must be (M, 3) and areas (M,); got {z.shape}, "
                             f"{n.shape}, {a.shape}.")
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
            if isinstance(b, Mirror) or not isinstance(b, (Lambertian, Phong)):
                raise ModelError(f"Patch {k} has a {type(b).__name__} BRDF; the symbolic model handles "
                                 "Lambertian and Phong patches (mirrors are image sources in the numeric "
                                 "model only). Replace it or estimate that scene numerically.")
        self.M = M
        self.z0 = z
        self.normals = n / np.linalg.norm(n, axis=1)[:, None]
        self.areas = a
        self.grid = grid
        self.irf = irf
        self.ill_ids = np.asarray(ill_ids, int)
        self.obs_ids = np.asarray(obs_ids, int)
        self.source = np.asarray(source, float)
        self.camera = self.source.copy() if camera is None else np.asarray(camera, float)
        self.phi = float(phi)
        self.legs_included = bool(legs_included)
        self.bounces = int(bounces)
        self.names = list(names) if names is not None else [f"P{k}" for k in range(M)]
        self.glossy = np.array([isinstance(b, Phong) for b in brdfs])
        if visibility is None:
            visibility = _facing(z, self.normals)
        self.visibility = np.asarray(visibility, bool)
        if self.visibility.shape != (M, M):
            raise ModelError(f"visibility must be ({M}, {M}); got {self.visibility.shape}.")
        self._params: dict[str, _Param] = {}
        for name, spec in PARAMETERS.items():
            if name == "position":
                val = z.copy()
            elif name == "distance":
                val = np.zeros((M, 2))
            elif name == "albedo":
                val = np.array([b.diffuse_albedo for b in brdfs], float)
            else:
                val = np.array([getattr(b, name, 0.0) for b in brdfs], float)
            shp = val.shape
            self._params[name] = _Param(name, val, np.zeros(M, bool), np.full(shp, spec["lower"]),
                                        np.full(shp, spec["upper"]), np.full(shp, spec["scale"]),
                                        np.zeros(shp))
        self.tilt_axis = np.array([_perpendicular(v) for v in self.normals])  # see set_tilt_axes
        self.anchors = -np.ones((M, 2), int)   # visible anchor patches of distance-parameterised patches
        self.anchor_dir = np.zeros((M, 3))      # fixed unit direction of the circle point (see set_hidden_distances)
        self.ids = None
        self._locked = False
        self.info = ModelInfo(bounces=self.bounces)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_scene(cls, scene, grid: TimeGrid, irf, bounces: int | None = None,
                   legs_included: bool = True) -> "TransientModel":
        """A model with the scene's geometry and BRDFs as fixed values (declare unknowns next)."""
        from .transport import needed_bounces

        if scene.has_mirrors:
            raise ModelError("The symbolic model has no mirror patches; this scene has "
                             f"{[k for k, b in enumerate(scene.brdfs) if isinstance(b, Mirror)]}.")
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

    def _patch_mask(self, patches) -> np.ndarray:
        if patches is None:
            return np.ones(self.M, bool)
        if isinstance(patches, str):
            table = {"all": np.ones(self.M, bool), "glossy": self.glossy.copy()}
            if patches not in table:
                raise ModelError(f"patches must be indices, a bool mask, 'all' or 'glossy'; got {patches!r}.")
            return table[patches]
        p = np.asarray(patches)
        if p.dtype == bool:
            if p.shape != (self.M,):
                raise ModelError(f"A patch mask must have shape ({self.M},); got {p.shape}.")
            return p.copy()
        m = np.zeros(self.M, bool)
        p = p.astype(int).ravel()
        if p.size and (p.min() < 0 or p.max() >= self.M):
            raise ModelError(f"patch indices must lie in 0..{self.M - 1}; got {p.tolist()}.")
        m[p] = True
        return m

    def set_unknown(self, name: str, patches=None, lower=None, upper=None, scale=None,
                    initial=None) -> "TransientModel":
        """Declare ``name`` unknown on ``patches`` (indices, mask, 'all', 'glossy').

        ``lower``/``upper``/``scale``/``initial`` broadcast to the selected patches (positions:
        (3,) or (k, 3)). Positions are parameterised as ``initial + scale * x`` (x about +-1
        within the bounds); BRDF parameters as ``scale * x``.
        """
        self._check_open("set_unknown")
        if name not in self._params:
            raise ModelError(f"Unknown parameter {name!r}; allowed: {sorted(self._params)}.")
        if name == "distance":
            raise ModelError("Hidden distances need anchors: call set_hidden_distances(patch, anchors, eps).")
        P = self._params[name]
        m = self._patch_mask(patches)
        if name in ("specular", "exponent") and np.any(m & ~self.glossy):
            bad = np.flatnonzero(m & ~self.glossy).tolist()
            raise ModelError(f"'{name}' is a Phong parameter; patches {bad} are Lambertian. Give them "
                             "a Phong BRDF (specular=0 is fine) or select patches='glossy'.")
        sel = np.flatnonzero(m)
        for attr, v in (("lower", lower), ("upper", upper), ("scale", scale), ("value", initial)):
            if v is not None:
                arr = getattr(P, attr)
                arr[sel] = np.broadcast_to(np.asarray(v, float), arr[sel].shape)
        if np.any(P.scale[sel] <= 0):
            raise ModelError(f"scale of '{name}' must be > 0; got {P.scale[sel].tolist()}.")
        if np.any(P.lower[sel] > P.upper[sel]):
            raise ModelError(f"lower > upper for '{name}' on patches {sel.tolist()}.")
        if name == "position":
            P.offset[sel] = P.value[sel]
        P.free |= m
        return self

    def set_hidden_distances(self, patch: int, anchors, eps: float, initial=None,
                             scale: float | None = None) -> "TransientModel":
        """Make patch ``patch``'s position a function of its distances to two fixed ``anchors``.

        p = a1 + x e + r u,  e = (a2 - a1)/L,  x = (d1^2 - d2^2 + L^2) / (2L),  r = sqrt(d1^2 - x^2),

        with u the unit vector perpendicular to e toward the current (initial) position, held fixed.
        The unknowns are the two distances (the paper's hidden distances, Fig. 12), bounded to
        ``initial +- eps``; the angle about the anchor axis stays the geometry stage's. Use it when
        the data see a hidden patch from two visible patches only (its position is then a circle).
        """
        self._check_open("set_hidden_distances")
        k = int(patch)
        a1, a2 = (int(a) for a in anchors)
        P = self._params["position"]
        if P.free[k] or P.free[a1] or P.free[a2]:
            raise ModelError(f"Patch {k}: distances need fixed anchors and a position that is not "
                             "itself unknown; call set_hidden_distances instead of set_unknown('position').")
        z = P.value
        e = z[a2] - z[a1]
        L = np.linalg.norm(e)
        e /= L
        v = z[k] - z[a1]
        perp = v - np.dot(v, e) * e
        if np.linalg.norm(perp) < 1e-9:
            raise ModelError(f"Patch {k} lies on the line through anchors {a1}, {a2}; pick other anchors.")
        self.anchors[k] = (a1, a2)
        self.anchor_dir[k] = perp / np.linalg.norm(perp)
        d0 = np.array([np.linalg.norm(z[k] - z[a1]), np.linalg.norm(z[k] - z[a2])])
        if initial is not None:
            d0 = np.asarray(initial, float)
        D = self._params["distance"]
        D.value[k] = d0
        D.lower[k] = d0 - eps
        D.upper[k] = d0 + eps
        D.scale[k] = eps if scale is None else scale
        D.offset[k] = d0
        D.free[k] = True
        return self

    def set_tilt_axes(self, patches, axis) -> "TransientModel":
        """Rotation axes of the normal unknowns ``"tilt"`` / ``"tilt2"`` on ``patches``.

        ``axis`` ((3,) or (k, 3)) is projected perpendicular to each patch's initial normal n0
        and normalised; ``tilt`` rotates n0 about it (n0 stays perpendicular to the axis), and
        ``tilt2`` tilts the normal toward it. Flatland scenes: the plane's normal, so that ``tilt``
        is the in-plane angle. Default axis: any unit vector perpendicular to n0.
        """
        self._check_open("set_tilt_axes")
        sel = np.flatnonzero(self._patch_mask(patches))
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

    def rotated_normals(self, tilt, tilt2):
        """Normals (M, 3) at tilt angles ``tilt``, ``tilt2`` ((M,) radians); NumPy or CasADi (3, M).

        The one formula for both: CasADi inputs give a (3, M) MX of columns, NumPy an (M, 3) array.
        """
        n0, ax = self.normals, self.tilt_axis
        u = np.cross(ax, n0)
        if isinstance(tilt, (ca.MX, ca.SX)) or isinstance(tilt2, (ca.MX, ca.SX)):
            a, b = ca.reshape(tilt, 1, self.M), ca.reshape(tilt2, 1, self.M)
            ca_, sa, cb, sb = ca.cos(a), ca.sin(a), ca.cos(b), ca.sin(b)
            rep = lambda v: ca.repmat(v, 3, 1)  # noqa: E731
            return rep(cb) * (rep(ca_) * ca.DM(n0.T) + rep(sa) * ca.DM(u.T)) + rep(sb) * ca.DM(ax.T)
        a = np.asarray(tilt, float)[:, None]
        b = np.asarray(tilt2, float)[:, None]
        return np.cos(b) * (np.cos(a) * n0 + np.sin(a) * u) + np.sin(b) * ax

    def set_general_brdf(self, patches, upper: float = 10.0 / math.pi,
                         scale: float = 1.0 / math.pi) -> "TransientModel":
        """Give ``patches`` a general, tabulated BRDF: one unknown f_kij per (k, i, j) met on a path.

        f_kij (1/sr) is the value of patch i's BRDF for light from k (a patch, or the source
        ``-1``) leaving toward j (a patch, or the camera ``-2``): the paper's general form-factor
        model. Start values are the patch's current diffuse albedo / pi; bounds [0, upper]. Use
        on small scenes: the number of unknowns grows as the number of (k, i, j) triples. The
        NLP adds Helmholtz reciprocity f_kij = f_jik (the source and camera count as one
        direction when co-located) and energy conservation over the patches as constraints.
        """
        self._check_open("set_general_brdf")
        m = self._patch_mask(patches)
        if np.any(m & self.glossy):
            raise ModelError("A patch with a Phong BRDF cannot also be general; pick Lambertian patches.")
        self.general = getattr(self, "general", np.zeros(self.M, bool)) | m
        self._general_bounds = (0.0, float(upper), float(scale))
        return self

    def fix(self, name: str, values, patches=None) -> "TransientModel":
        """Fix ``name`` to ``values`` on ``patches`` (no longer unknown there)."""
        self._check_open("fix")
        if name not in self._params:
            raise ModelError(f"Unknown parameter {name!r}; allowed: {sorted(self._params)}.")
        P = self._params[name]
        m = self._patch_mask(patches)
        sel = np.flatnonzero(m)
        P.value[sel] = np.broadcast_to(np.asarray(values, float), P.value[sel].shape)
        P.free &= ~m
        return self

    # ------------------------------------------------------------------ setup
    def setup(self) -> "TransientModel":
        """Check the declaration, enumerate paths, build the CasADi graph and lock the model."""
        self._check_open("setup")
        t0 = time.perf_counter()
        blocks = []
        for name, P in self._params.items():
            for k in np.flatnonzero(P.free):
                for c in range(P.width):
                    idx = (k,) if P.width == 1 else (k, c)
                    lo, hi = P.lower[idx], P.upper[idx]
                    v = P.value[idx]
                    if not (lo - 1e-12 <= v <= hi + 1e-12):
                        raise ModelError(f"Initial {name} of patch {k} ({self.names[k]}) = {v:.6g} lies "
                                         f"outside its bounds [{lo:.6g}, {hi:.6g}]; pass initial= inside.")
                    blocks.append((name, k, c))
        self.general = getattr(self, "general", np.zeros(self.M, bool))
        self.triples = np.zeros((0, 3), int)
        if self.general.any():
            if self._params["albedo"].free[self.general].any():
                raise ModelError("A general-BRDF patch has no albedo unknown (its f_kij are the unknowns); "
                                 "declare set_unknown('albedo', ...) on the other patches only.")
            self.triples = self._general_triples()
            lo_, hi_, sc_ = self._general_bounds
            T = len(self.triples)
            f0 = self._params["albedo"].value[self.triples[:, 1]] / math.pi
            self._params["fkij"] = _Param("fkij", f0.copy(), np.ones(T, bool), np.full(T, lo_),
                                          np.full(T, hi_), np.full(T, sc_), np.zeros(T))
            blocks += [("fkij", t, 0) for t in range(T)]
        if not blocks:
            raise ModelError("No unknowns declared: call set_unknown('albedo', ...) (or 'specular', "
                             "'exponent', 'position') before setup().")
        pos = self._params["position"]
        if (pos.free.any() or self._params["distance"].free.any()) and not getattr(self.irf, "band_limited", False):
            raise ModelError("Unknown positions need a differentiable delay kernel: a GaussianIRF "
                             f"impulse response; got {getattr(self.irf, 'describe', lambda: self.irf)()}. "
                             "Fix the positions or give the model a GaussianIRF.")
        self.blocks = blocks
        self.n_x = len(blocks)
        self.x_names = [self._triple_name(k) if n == "fkij" else
                        f"{n}[{self.names[k]}]" + ("" if self._params[n].width == 1 else "xyz"[c])
                        for n, k, c in blocks]
        sc = np.array([self._val(self._params[n].scale, k, c) for n, k, c in blocks])
        off = np.array([self._val(self._params[n].offset, k, c) for n, k, c in blocks])
        lo = np.array([self._val(self._params[n].lower, k, c) for n, k, c in blocks])
        hi = np.array([self._val(self._params[n].upper, k, c) for n, k, c in blocks])
        v0 = np.array([self._val(self._params[n].value, k, c) for n, k, c in blocks])
        self.x_scale, self.x_offset = sc, off
        self.lbx, self.ubx = (lo - off) / sc, (hi - off) / sc
        self.x0 = (v0 - off) / sc
        self.x = ca.MX.sym("x", self.n_x)
        self.theta_sym = self._theta_expressions(self.x)
        if not hasattr(self, "paths"):
            self._enumerate_paths()
        self.y_sym = self._output(self.theta_sym)
        self.f_y = ca.Function("stir_model", [self.x], [self.y_sym], ["x"], ["y"])
        self._locked = True
        self.info.n_unknowns = self.n_x
        self.info.build_time_s = time.perf_counter() - t0
        return self

    def _end_name(self, e):
        return {-1: "src", -2: "cam"}.get(int(e), self.names[int(e)] if e >= 0 else str(e))

    def _triple_name(self, t):
        k, i, j = self.triples[t]
        return f"f[{self._end_name(k)},{self.names[i]},{self._end_name(j)}]"

    def _general_triples(self) -> np.ndarray:
        """Every (prev, patch, next) met on a path at a general patch (-1 source, -2 camera)."""
        # enumeration does not depend on the unknowns: reuse the path lists
        if not hasattr(self, "paths"):
            self._enumerate_paths()
        out = set()
        for g in self.paths:
            v = g.verts
            n = v.shape[1]
            for m_ in range(n):
                prev = v[:, m_ - 1] if m_ > 0 else np.full(len(v), -1)
                nxt = v[:, m_ + 1] if m_ < n - 1 else np.full(len(v), -2)
                sel = self.general[v[:, m_]]
                out.update(zip(prev[sel].tolist(), v[sel, m_].tolist(), nxt[sel].tolist()))
        return np.array(sorted(out), int).reshape(-1, 3)

    def triple_index(self, prev, i, nxt) -> np.ndarray:
        key = {tuple(t): n for n, t in enumerate(self.triples.tolist())}
        return np.array([key[(int(a), int(b), int(c))] for a, b, c in zip(prev, i, nxt)], int)

    @staticmethod
    def _val(arr, k, c):
        return float(arr[k] if arr.ndim == 1 else arr[k, c])

    def _require_setup(self, what: str):
        if not self._locked:
            raise ModelError(f"{what} needs a set-up model: call model.setup() first.")

    @property
    def is_setup(self) -> bool:
        return self._locked

    def param(self, name: str) -> _Param:
        return self._params[name]

    # ------------------------------------------------------------------ symbolic parameters
    def _theta_expressions(self, x):
        """Per-parameter symbolic arrays: scalar params as (M,1) MX, positions as (3, M) MX."""
        out = {}
        for name, P in self._params.items():
            base = P.value.copy()
            idx = [(j, k, c) for j, (n, k, c) in enumerate(self.blocks) if n == name]
            if P.width == 1:
                base[P.free] = 0.0
                expr = ca.MX(ca.DM(base))
                if idx:
                    rows = [k for _, k, _ in idx]
                    cols = [j for j, _, _ in idx]
                    vals = [self.x_scale[j] for j, _, _ in idx]
                    S = ca.DM(ca.Sparsity.triplet(len(base), self.n_x, rows, cols), vals)
                    offs = np.zeros(len(base))
                    for j, k, _ in idx:
                        offs[k] = self.x_offset[j]
                    expr = expr + ca.DM(offs) + ca.mtimes(S, x)
            else:
                W = P.width
                base = base.T.copy()  # (W, M), column-major flatten = patch-major
                for _, k, c in idx:
                    base[c, k] = 0.0
                flat = ca.MX(ca.DM(base.T.ravel()))  # index W k + c
                if idx:
                    rows = [W * k + c for _, k, c in idx]
                    cols = [j for j, _, _ in idx]
                    vals = [self.x_scale[j] for j, _, _ in idx]
                    S = ca.DM(ca.Sparsity.triplet(W * self.M, self.n_x, rows, cols), vals)
                    offs = np.zeros(W * self.M)
                    for j, k, c in idx:
                        offs[W * k + c] = self.x_offset[j]
                    flat = flat + ca.DM(offs) + ca.mtimes(S, x)
                expr = ca.reshape(flat, W, self.M)
            out[name] = expr
        dfree = np.flatnonzero(self._params["distance"].free)
        if len(dfree):
            Z = out["position"]
            cols = [Z[:, k] for k in range(self.M)]
            for k in dfree:
                cols[k] = self._trilaterate(k, out["distance"][0, k], out["distance"][1, k])
            out["position"] = ca.horzcat(*cols)
        if self.tilt_free.any():
            out["normal"] = self.rotated_normals(out["tilt"], out["tilt2"])
        else:
            out["normal"] = ca.MX(ca.DM(self.normals.T))
        return out

    @property
    def tilt_free(self) -> np.ndarray:
        """(M,) bool: patches whose normal is unknown (``tilt`` or ``tilt2``)."""
        return self._params["tilt"].free | self._params["tilt2"].free

    def _trilaterate(self, k, d1, d2):
        """Position of a distance-parameterised patch (see ``set_hidden_distances``); NumPy or CasADi."""
        a1, a2 = self.anchors[k]
        z = self._params["position"].value
        e = z[a2] - z[a1]
        L = float(np.linalg.norm(e))
        e = e / L
        xx = (d1 * d1 - d2 * d2 + L * L) / (2.0 * L)
        if isinstance(d1, (ca.MX, ca.SX)):
            r = ca.sqrt(ca.fmax(d1 * d1 - xx * xx, 1e-12))
            return ca.DM(z[a1]) + xx * ca.DM(e) + r * ca.DM(self.anchor_dir[k])
        r = math.sqrt(max(d1 * d1 - xx * xx, 1e-12))
        return z[a1] + xx * e + r * self.anchor_dir[k]

    def theta(self, x) -> dict:
        """Numeric parameter values (albedo, specular, exponent, tilt, tilt2: (M,); position: (M, 3))
        at x, and the resulting unit ``normal`` (M, 3)."""
        self._require_setup("theta()")
        x = np.asarray(x, float).ravel()
        out = {n: P.value.copy() for n, P in self._params.items()}
        for j, (n, k, c) in enumerate(self.blocks):
            v = self.x_offset[j] + self.x_scale[j] * x[j]
            if out[n].ndim == 1:
                out[n][k] = v
            else:
                out[n][k, c] = v
        for k in np.flatnonzero(self._params["distance"].free):
            out["position"][k] = self._trilaterate(k, out["distance"][k, 0], out["distance"][k, 1])
        out["normal"] = self.rotated_normals(out["tilt"], out["tilt2"])
        return out

    def x_of(self, values: dict) -> np.ndarray:
        """Scaled decision vector for parameter values given by name (missing: the model's)."""
        self._require_setup("x_of()")
        x = np.empty(self.n_x)
        for j, (n, k, c) in enumerate(self.blocks):
            arr = np.asarray(values.get(n, self._params[n].value), float)
            v = arr[k] if arr.ndim == 1 else arr[k, c]
            x[j] = (v - self.x_offset[j]) / self.x_scale[j]
        return x

    # ------------------------------------------------------------------ paths
    def _enumerate_paths(self):
        M, K = self.M, self.bounces
        vis = self.visibility
        ill_row = -np.ones(M, int)
        ill_row[self.ill_ids] = np.arange(len(self.ill_ids))
        obs_col = -np.ones(M, int)
        obs_col[self.obs_ids] = np.arange(len(self.obs_ids))
        moving = self._params["position"].free | self._params["distance"].free
        n_obs = len(self.obs_ids)
        groups = []
        front = self.ill_ids.reshape(-1, 1)
        for n in range(1, K + 1):
            if n > 1:
                a_idx, b_idx = np.nonzero(vis[front[:, -1]])
                front = np.concatenate([front[a_idx], b_idx[:, None]], axis=1)
            keep = obs_col[front[:, -1]] >= 0
            verts = front[keep]
            if len(verts):
                trace = ill_row[verts[:, 0]] * n_obs + obs_col[verts[:, -1]]
                var = moving[verts].any(axis=1)
                groups.append(Paths(verts, trace, var))
        self.paths = groups
        # windows: tau at the initial geometry +- the largest change the position bounds allow
        w, t0, nb = self.grid.bin_width, self.grid.start, self.grid.n_bins
        lo_s, hi_s = self.irf.support()
        P = self._params["position"]
        reach = np.zeros(M)
        if moving.any():
            d_lo = np.abs(P.lower - P.value)
            d_hi = np.abs(P.upper - P.value)
            reach = np.sqrt(np.sum(np.maximum(d_lo, d_hi) ** 2, axis=1))
            Dp = self._params["distance"]
            for k in np.flatnonzero(Dp.free):  # corners of the distance box
                pts = [self._trilaterate(k, a, b) for a in (Dp.lower[k, 0], Dp.upper[k, 0])
                       for b in (Dp.lower[k, 1], Dp.upper[k, 1])]
                reach[k] = max(np.linalg.norm(q - P.value[k]) for q in pts) + 1e-9
            reach[~moving] = 0.0
            if not np.all(np.isfinite(reach[moving])):
                raise ModelError("Unknown positions need finite lower/upper bounds (the geometry "
                                 "stage's error bound): pass lower=/upper= to set_unknown('position').")
        tr_lo = np.full(len(self.ill_ids) * n_obs, np.iinfo(np.int64).max)
        tr_hi = np.full(len(self.ill_ids) * n_obs, -1)
        self._win = []
        for g in groups:
            tau = self._tau_numeric(g.verts, self._params["position"].value)
            slack = 2.0 * reach[g.verts].sum(axis=1)  # each moving vertex touches <= 2 legs
            k0 = np.floor((tau - slack + lo_s - t0) / w).astype(np.int64)
            k1 = np.ceil((tau + slack + hi_s - t0) / w).astype(np.int64) + 1
            k0c, k1c = np.clip(k0, 0, nb), np.clip(k1, 0, nb)
            ok = k1c > k0c
            np.minimum.at(tr_lo, g.trace[ok], k0c[ok])
            np.maximum.at(tr_hi, g.trace[ok], k1c[ok])
            self._win.append((k0, k1))
        has = tr_hi > tr_lo
        self.trace_lo = np.where(has, tr_lo, 0)
        self.trace_hi = np.where(has, tr_hi, 0)
        seg_len = self.trace_hi - self.trace_lo
        self.seg_start = np.concatenate([[0], np.cumsum(seg_len)])
        self.n_support = int(self.seg_start[-1])
        # flat indices of the support into stir.reshape(-1)
        tr = np.repeat(np.arange(len(seg_len)), seg_len)
        kk = np.arange(self.n_support) - np.repeat(self.seg_start[:-1], seg_len) + np.repeat(self.trace_lo, seg_len)
        self.support = tr * nb + kk
        self.support_trace = tr
        self.info.n_paths = int(sum(len(g.verts) for g in groups))
        self.info.n_variable_paths = int(sum(int(g.variable.sum()) for g in groups))
        self.info.n_support = self.n_support

    def _tau_numeric(self, verts, z):
        tau = np.zeros(len(verts))
        for m in range(verts.shape[1] - 1):
            tau += np.linalg.norm(z[verts[:, m + 1]] - z[verts[:, m]], axis=1)
        if self.legs_included:
            tau += np.linalg.norm(z[verts[:, 0]] - self.source, axis=1)
            tau += np.linalg.norm(z[verts[:, -1]] - self.camera, axis=1)
        return tau

    # ------------------------------------------------------------------ output
    def _path_amp_tau(self, verts, th):
        """Symbolic (1, P) amplitude and delay of paths ``verts`` (P, n) with parameters ``th``."""
        Z = th["position"]                       # (3, M) MX
        N = th["normal"]                         # (3, M) MX (constant unless tilts are free)
        P_, n = verts.shape
        alb, spec, expo = th["albedo"], th["specular"], th["exponent"]
        zs = [Z[:, verts[:, m].tolist()] for m in range(n)]
        src = ca.DM(self.source)
        cam = ca.DM(self.camera)

        def unit_to(a, b):  # unit vector from a to b (3, P) and the distance (1, P)
            v = b - a
            d = ca.sqrt(ca.sum1(v * v))
            return v / ca.repmat(d, 3, 1), d

        def dot(a, b):
            return ca.sum1(a * b)

        # directions at each vertex toward the previous and next point
        w_prev, w_next, legs = [], [], []
        to_src, d_src = unit_to(zs[0], ca.repmat(src, 1, P_))
        to_cam, d_cam = unit_to(zs[-1], ca.repmat(cam, 1, P_))
        for m in range(n - 1):
            u, d = unit_to(zs[m], zs[m + 1])
            legs.append((u, d))
        for m in range(n):
            w_prev.append(to_src if m == 0 else -legs[m - 1][0])
            w_next.append(to_cam if m == n - 1 else legs[m][0])
        amp = ca.DM(source_irradiance(self.phi, self.areas[verts[:, 0]])).T
        for m in range(n):
            vk = verts[:, m]
            nk = N[:, vk.tolist()]
            ci, co, cio = dot(w_prev[m], nk), dot(w_next[m], nk), dot(w_prev[m], w_next[m])
            rho = alb[vk.tolist()].T
            f = Lambertian.formula(ci, co, cio, rho)
            ge = self.general[vk]
            if ge.any():
                prev = verts[:, m - 1] if m > 0 else np.full(P_, -1)
                nxt = verts[:, m + 1] if m < n - 1 else np.full(P_, -2)
                idx = np.zeros(P_, int)
                idx[ge] = self.triple_index(prev[ge], vk[ge], nxt[ge])
                fg = th["fkij"][idx.tolist()].T
                mask = ca.DM(ge.astype(float)).T
                f = mask * fg + (1.0 - mask) * f
            gl = self.glossy[vk]
            if gl.any():
                fp = Phong.formula(ci, co, cio, rho, spec[vk.tolist()].T, expo[vk.tolist()].T)
                mask = ca.DM(gl.astype(float)).T
                f = mask * fp + (1.0 - mask) * f
            amp = amp * f
        tau = ca.DM.zeros(1, P_)
        for m, (u, d) in enumerate(legs):
            a_src = ca.DM(self.areas[verts[:, m]]).T
            c_src = dot(u, N[:, verts[:, m].tolist()])
            c_dst = -dot(u, N[:, verts[:, m + 1].tolist()])
            amp = amp * form_factor(a_src, c_src, c_dst, d)
            tau = tau + d
        if self.legs_included:
            tau = tau + d_src + d_cam
        return amp, tau

    def _output(self, th):
        """Symbolic STIR on the support bins (n_support,) = A_fixed @ amp_fixed + y_variable.

        Also kept for structured costs (``stircasadi.estimate.nlp`` folds traces): ``A_fixed``
        (scipy CSC, n_support x n_fixed_paths, constant kernels), ``amp_fixed`` (MX), ``y_var``
        (MX, the symbolic-kernel paths), ``fixed_trace`` (trace of each fixed path) and
        ``variable_traces`` (bool per trace).
        """
        from scipy import sparse

        w, t0, nb = self.grid.bin_width, self.grid.start, self.grid.n_bins
        y = ca.MX.zeros(self.n_support, 1)
        y_var = ca.MX(self.n_support, 1)
        A_blocks, amps, ftr = [], [], []
        var_tr = np.zeros(len(self.trace_lo), bool)
        for g, (k0, k1) in zip(self.paths, self._win):
            pos_of_bin = lambda tr, k: self.seg_start[tr] + (k - self.trace_lo[tr])  # noqa: E731
            fixed = np.flatnonzero(~g.variable)
            if len(fixed):
                vf = g.verts[fixed]
                amp, _ = self._path_amp_tau(vf, th)
                tau = self._tau_numeric(vf, self._params["position"].value)
                rows, cols, vals = [], [], []
                kmax = int(np.max(k1[fixed] - k0[fixed]))
                offs = np.arange(kmax)
                kk = k0[fixed, None] + offs[None, :]
                valid = (kk >= 0) & (kk < nb) & (kk < k1[fixed, None])
                left = t0 + kk * w - tau[:, None]
                h = bin_integral(self.irf, left, w)
                pi, mi = np.nonzero(valid)
                tr = g.trace[fixed][pi]
                rows = pos_of_bin(tr, kk[pi, mi])
                vals = h[pi, mi]
                nz = vals != 0.0
                A_blocks.append(sparse.csc_matrix((vals[nz], (rows[nz], pi[nz])),
                                                  shape=(self.n_support, len(fixed))))
                amps.append(amp.T)
                ftr.append(g.trace[fixed])
            var = np.flatnonzero(g.variable)
            if len(var):
                vv = g.verts[var]
                amp, tau = self._path_amp_tau(vv, th)
                kmax = int(np.max(k1[var] - k0[var]))
                offs = np.arange(kmax)
                kk = k0[var, None] + offs[None, :]
                valid = (kk >= 0) & (kk < nb) & (kk < k1[var, None])
                left = ca.DM(t0 + kk * w)                                   # (P, W)
                T = ca.repmat(tau.T, 1, kmax)
                H = bin_integral(self.irf, left - T, w)
                C = H * ca.repmat(amp.T, 1, kmax)
                pi, mi = np.nonzero(valid)
                rows = pos_of_bin(g.trace[var][pi], kk[pi, mi])
                cols = mi * len(var) + pi                                    # column-major vec
                Sc = ca.DM(ca.Sparsity.triplet(self.n_support, len(var) * kmax, rows.tolist(),
                                               cols.tolist()), np.ones(len(rows)))
                y_var = y_var + ca.mtimes(Sc, ca.vec(C))
                var_tr[g.trace[var]] = True
        if A_blocks:
            A = sparse.hstack(A_blocks).tocsc()
            self.A_fixed = A
            self.amp_fixed = ca.vertcat(*amps)
            self.fixed_trace = np.concatenate(ftr)
            Acs = ca.DM(ca.Sparsity(A.shape[0], A.shape[1], A.indptr.tolist(), A.indices.tolist()),
                        A.data)
            y = ca.mtimes(Acs, self.amp_fixed)
        else:
            self.A_fixed, self.amp_fixed, self.fixed_trace = None, None, np.zeros(0, int)
        self.y_var = y_var
        self.variable_traces = var_tr
        return y + y_var

    # ------------------------------------------------------------------ numeric evaluation
    def evaluate(self, x=None) -> np.ndarray:
        """Model STIR on the support bins at scaled ``x`` (default: the initial guess x0)."""
        self._require_setup("evaluate()")
        x = self.x0 if x is None else np.asarray(x, float)
        return np.asarray(self.f_y(x)).ravel()

    def simulate(self, x=None) -> np.ndarray:
        """Full STIR (n_ill, n_obs, n_bins) at scaled ``x`` (default x0): zero off the support."""
        out = np.zeros(len(self.ill_ids) * len(self.obs_ids) * self.grid.n_bins)
        out[self.support] = self.evaluate(x)
        return out.reshape(len(self.ill_ids), len(self.obs_ids), self.grid.n_bins)

    def data_on_support(self, stir) -> np.ndarray:
        """The measured STIR (n_ill, n_obs, n_bins) restricted to the model's support bins."""
        self._require_setup("data_on_support()")
        stir = np.asarray(stir, float)
        want = (len(self.ill_ids), len(self.obs_ids), self.grid.n_bins)
        if stir.shape != want:
            raise ModelError(f"The data STIR has shape {stir.shape}; this model expects {want} "
                             "(n_illuminated, n_observed, n_bins).")
        return stir.reshape(-1)[self.support]

    def energy_terms(self, th):
        """Symbolic flux-transfer column sums c_k = sum_r rho_r F_{k->r} (M,).

        ``F_{k->r} = a_r cos_k cos_r / (pi d^2)`` is the fraction of k's diffuse emission landing on
        r; the flux-transfer matrix ``K_rk = rho_r F_{k->r}`` is similar to the transfer operator
        of the transient equation, so ``max_k c_k < 1`` bounds its spectral radius below 1
        (stable, energy-conserving transport). For Phong patches rho = albedo + specular.
        """
        Z = th["position"]
        h, r = np.nonzero(self.visibility)
        zh, zr = Z[:, h.tolist()], Z[:, r.tolist()]
        v = zr - zh
        d = ca.sqrt(ca.sum1(v * v))
        u = v / ca.repmat(d, 3, 1)
        N = th["normal"] if "normal" in th else ca.DM(self.normals.T)
        ch = ca.sum1(u * N[:, h.tolist()])
        cr = -ca.sum1(u * N[:, r.tolist()])
        F = form_factor(ca.DM(self.areas[r]).T, ch, cr, d) / math.pi
        refl = th["albedo"] + th["specular"] * ca.DM(self.glossy.astype(float))
        terms = F * refl[r.tolist()].T
        S = ca.DM(ca.Sparsity.triplet(self.M, len(h), h.tolist(), list(range(len(h)))), np.ones(len(h)))
        return ca.mtimes(S, terms.T)


def _perpendicular(n):
    """A unit vector perpendicular to the unit vector n (the default tilt axis)."""
    e = np.eye(3)[int(np.argmin(np.abs(n)))]
    v = e - np.dot(e, n) * n
    return v / np.linalg.norm(v)


def _facing(z, n):
    M = len(z)
    vec = z[None, :, :] - z[:, None, :]
    d = np.linalg.norm(vec, axis=-1)
    np.fill_diagonal(d, 1.0)
    u = vec / d[..., None]
    ck = np.einsum("kid,kd->ki", u, n)
    ci = -np.einsum("kid,id->ki", u, n)
    vis = (ck > 0) & (ci > 0)
    np.fill_diagonal(vis, False)
    return vis & ~np.eye(M, dtype=bool)
