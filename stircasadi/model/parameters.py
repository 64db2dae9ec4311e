"""The unknown registry of the symbolic model: names, bounds, scales, and x <-> theta.

Every per-patch quantity the model can estimate is a named parameter (``SPEC``). A parameter is
*declared* unknown on some patches (with bounds, a scale and an initial value) or stays fixed at
its value. The NLP sees one decision vector ``x`` of scaled unknowns (each about 0.1-100 inside
its bounds, STYLE.md rule 7):

    theta = offset + scale * x                         (scalar parameters)
    z_k   = z0_k + B_k (scale_k * x_k)                 (positions: a basis B_k of 1-3 columns:
                                                        a camera ray, a plane, or free 3-D)

``ParameterSet.lock()`` freezes the declaration; ``theta_sym(x)`` gives the CasADi expressions
(one sparse linear map per parameter, no per-patch graph nodes), ``theta(x)`` the numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ModelError

__all__ = ["SPEC", "Param", "ParameterSet"]

#: name -> (lower, upper, scale, width): default bounds, scale and per-patch width.
SPEC = {
    "albedo": (0.0, 1.0, 1.0, 1),
    "area": (1e-8, 1.0, 1e-3, 1),
    "specular": (0.0, 1.0, 1.0, 1),
    "exponent": (0.0, 500.0, 10.0, 1),
    "position": (-np.inf, np.inf, 0.01, 3),
    # normal rotations (radians): n = cos(b) (cos(a) n0 + sin(a) (ax x n0)) + sin(b) ax, with
    # a = tilt about the patch's tilt axis ax (perpendicular to n0) and b = tilt2 toward ax
    "tilt": (-math.radians(80.0), math.radians(80.0), 1.0, 1),
    "tilt2": (-math.radians(80.0), math.radians(80.0), 1.0, 1),
}


@dataclass
class Param:
    """One named parameter over the M patches (values are the fixed values / initial guesses)."""

    name: str
    value: np.ndarray        # (M,) or (M, 3)
    free: np.ndarray         # (M,) bool
    lower: np.ndarray        # (M,) or (M, 3) (positions: in basis coordinates, metres)
    upper: np.ndarray
    scale: np.ndarray
    offset: np.ndarray       # scalars: theta = offset + scale x; positions unused (z0 = value)

    @property
    def width(self) -> int:
        return 1 if self.value.ndim == 1 else self.value.shape[1]


class ParameterSet:
    """The declared unknowns of a model over M patches (see the module docstring)."""

    def __init__(self, M: int, values: dict):
        self.M = M
        self._p: dict[str, Param] = {}
        for name, (lo, hi, sc, width) in SPEC.items():
            v = np.array(values[name], float)
            shp = v.shape
            self._p[name] = Param(name, v, np.zeros(M, bool), np.full(shp, lo), np.full(shp, hi),
                                  np.full(shp, sc), np.zeros(shp))
        self.basis = np.tile(np.eye(3)[None], (M, 1, 1))   # (M, 3, 3): position basis columns
        self.dims = np.full(M, 3)                            # free position dimensions per patch
        self.locked = False

    # ------------------------------------------------------------------ declaration
    def __getitem__(self, name: str) -> Param:
        if name not in self._p:
            raise ModelError(f"Unknown parameter {name!r}; allowed: {sorted(self._p)}.")
        return self._p[name]

    def names(self):
        return list(self._p)

    def _open(self, what):
        if self.locked:
            raise ModelError(f"The model is set up and locked; {what} must come before setup(). "
                             "Build a new model to change its unknowns.")

    def declare(self, name: str, sel: np.ndarray, lower=None, upper=None, scale=None, initial=None,
                basis=None):
        """Make ``name`` unknown on the patches ``sel`` (indices)."""
        self._open("set_unknown")
        P = self[name]
        if name == "position":
            if basis is not None:
                Bm = np.asarray(basis, float)
                Bm = np.broadcast_to(Bm, (len(sel),) + Bm.shape[-2:]) if Bm.ndim == 2 else Bm
                if Bm.shape[0] != len(sel) or Bm.shape[1] != 3 or not 1 <= Bm.shape[2] <= 3:
                    raise ModelError(f"position basis must be (3, d) or (k, 3, d) with d in 1..3; got {Bm.shape}.")
                for i, k in enumerate(sel):
                    q, _ = np.linalg.qr(Bm[i])
                    q[np.abs(q) < 1e-13] = 0.0   # exact zeros: a plane or ray along an axis stays on it
                    self.basis[k] = 0.0
                    self.basis[k][:, :Bm.shape[2]] = q[:, :Bm.shape[2]]
                    self.dims[k] = Bm.shape[2]
            if initial is not None:
                P.value[sel] = np.broadcast_to(np.asarray(initial, float), P.value[sel].shape)
        for attr, v in (("lower", lower), ("upper", upper), ("scale", scale)):
            if v is not None:
                arr = getattr(P, attr)
                arr[sel] = np.broadcast_to(np.asarray(v, float), arr[sel].shape)
        if initial is not None and name != "position":
            P.value[sel] = np.broadcast_to(np.asarray(initial, float), P.value[sel].shape)
        if np.any(P.scale[sel] <= 0):
            raise ModelError(f"scale of '{name}' must be > 0; got {P.scale[sel].tolist()}.")
        if np.any(P.lower[sel] > P.upper[sel]):
            raise ModelError(f"lower > upper for '{name}' on patches {np.asarray(sel).tolist()}.")
        P.free[sel] = True

    def fix(self, name: str, sel: np.ndarray, values):
        self._open("fix")
        P = self[name]
        P.value[sel] = np.broadcast_to(np.asarray(values, float), P.value[sel].shape)
        P.free[sel] = False

    # ------------------------------------------------------------------ lock
    def lock(self, patch_names) -> None:
        """Freeze the declaration: decision-vector layout, bounds, scales, names, x0."""
        blocks = []
        for name, P in self._p.items():
            for k in np.flatnonzero(P.free):
                width = int(self.dims[k]) if name == "position" else P.width
                for c in range(width):
                    blocks.append((name, int(k), c))
        self.blocks = blocks
        self.n_x = len(blocks)
        lo, hi, sc, off, v0 = (np.empty(self.n_x) for _ in range(5))
        for j, (name, k, c) in enumerate(blocks):
            P = self._p[name]
            if name == "position":
                lo[j], hi[j], sc[j] = P.lower[k, c], P.upper[k, c], P.scale[k, c]
                off[j], v0[j] = 0.0, 0.0
            else:
                lo[j], hi[j], sc[j], off[j], v0[j] = P.lower[k], P.upper[k], P.scale[k], P.offset[k], P.value[k]
                if not (lo[j] - 1e-12 <= v0[j] <= hi[j] + 1e-12):
                    raise ModelError(f"Initial {name} of patch {k} ({patch_names[k]}) = {v0[j]:.6g} lies "
                                     f"outside its bounds [{lo[j]:.6g}, {hi[j]:.6g}]; pass initial= inside.")
        for k in np.flatnonzero(self._p["position"].free):
            d = int(self.dims[k])
            P = self._p["position"]
            if np.any(P.lower[k, :d] > 1e-12) or np.any(P.upper[k, :d] < -1e-12):
                raise ModelError(f"Position bounds of patch {k} ({patch_names[k]}) are offsets from its "
                                 f"initial position in its basis and must contain 0; got "
                                 f"[{P.lower[k, :d].tolist()}, {P.upper[k, :d].tolist()}].")
        self.x_scale, self.x_offset = sc, off
        self.lbx, self.ubx = (lo - off) / sc, (hi - off) / sc
        self.x0 = (v0 - off) / sc
        self.x_names = [f"{n}[{patch_names[k]}]" + ("" if self._p[n].width == 1 else
                                                    ("xyz"[c] if self.dims[k] == 3 else f"u{c}"))
                        for n, k, c in blocks]
        self.locked = True

    # ------------------------------------------------------------------ x <-> theta
    def theta_sym(self, x) -> dict:
        """CasADi expressions: scalar parameters (M, 1); positions (3, M)."""
        out = {}
        for name, P in self._p.items():
            idx = [(j, k, c) for j, (n, k, c) in enumerate(self.blocks) if n == name]
            if name == "position":
                base = ca.DM(P.value.T)                              # (3, M) initial positions
                if idx:
                    rows_, cols, vals = [], [], []
                    for j, k, c in idx:
                        for r in range(3):
                            b = self.basis[k][r, c]
                            if b != 0.0:
                                rows_.append(3 * k + r)
                                cols.append(j)
                                vals.append(b * self.x_scale[j])
                    S = ca.DM(ca.Sparsity.triplet(3 * self.M, self.n_x, rows_, cols), vals)
                    out[name] = base + ca.reshape(ca.mtimes(S, x), 3, self.M)
                else:
                    out[name] = ca.MX(base)
                continue
            base = P.value.copy()
            base[P.free] = 0.0
            expr = ca.MX(ca.DM(base))
            if idx:
                rows_ = [k for _, k, _ in idx]
                cols = [j for j, _, _ in idx]
                S = ca.DM(ca.Sparsity.triplet(self.M, self.n_x, rows_, cols), [self.x_scale[j] for j in cols])
                offs = np.zeros(self.M)
                for j, k, _ in idx:
                    offs[k] = self.x_offset[j]
                expr = expr + ca.DM(offs) + ca.mtimes(S, x)
            out[name] = expr
        return out

    def theta(self, x) -> dict:
        """Numeric values at x: scalar parameters (M,), positions (M, 3)."""
        x = np.asarray(x, float).ravel()
        out = {n: P.value.copy() for n, P in self._p.items()}
        for j, (n, k, c) in enumerate(self.blocks):
            v = self.x_scale[j] * x[j]
            if n == "position":
                out[n][k] += self.basis[k][:, c] * v
            else:
                out[n][k] = self.x_offset[j] + v
        return out

    def x_of(self, values: dict) -> np.ndarray:
        """Scaled decision vector for parameter values by name (missing: the declared values);
        positions are projected on their basis."""
        x = np.empty(self.n_x)
        for j, (n, k, c) in enumerate(self.blocks):
            P = self._p[n]
            arr = np.asarray(values.get(n, P.value), float)
            if n == "position":
                x[j] = float(self.basis[k][:, c] @ (arr[k] - P.value[k])) / self.x_scale[j]
            else:
                x[j] = (arr[k] - self.x_offset[j]) / self.x_scale[j]
        return x

    def position_jacobian(self) -> np.ndarray:
        """(M, 3, n_x) d z_k / d x (constant: positions are linear in x)."""
        J = np.zeros((self.M, 3, self.n_x))
        for j, (n, k, c) in enumerate(self.blocks):
            if n == "position":
                J[k, :, j] = self.basis[k][:, c] * self.x_scale[j]
        return J
