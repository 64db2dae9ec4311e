"""Scenes: small planar patches, a pulsed source and a directional camera.

When to use
-----------
Build a ``Scene`` from a list of ``Patch`` (problem scripts) or from a mesh file with
``Scene.from_mesh`` (OBJ/PLY/STL via trimesh, split into patches of a requested size). The scene
describes; it never simulates (``stircasadi.transport`` does).

Visibility
----------
* between patches: a leg k -> i exists when both patches face each other (cosines > 0) and, when
  the scene has occluders (an occluder mesh, or ``self_occlusion`` for mesh scenes), no triangle
  blocks the segment (ray casting with trimesh). Without occluders no ray is cast at all
  (DESIGN.md section 7).
* to the camera / from the source: a patch is *visible* when it faces the camera, is not
  occluded and is not declared ``hidden``; it is *illuminable* under the same rule for the
  source. Hidden patches are neither illuminated nor observed: they are what the inverse problem
  must find from third-bounce light.

The small-patch approximation needs patch sizes well below inter-patch distances;
``Scene.check_physics`` warns when a patch's form-factor row sum exceeds 1 (energy would be
created) and names the patches to subdivide.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from .brdf import BRDF, Lambertian, Mirror, Phong
from .errors import PhysicsWarning, SceneError
from .radiometry import facing_matrix

_UNIT_TOL = 1e-6


@dataclass(frozen=True)
class Patch:
    """A small planar patch.

    Parameters
    ----------
    centre : (3,) metres.
    normal : (3,) unit normal (|n| = 1 within 1e-6; normalise it yourself if needed).
    area : m^2, > 0.
    brdf : Lambertian | Phong | Mirror.
    hidden : declare the patch invisible to the camera and the source even when geometry alone
        would show it (e.g. behind an occluder that is not modelled).
    name : optional label.
    """

    centre: tuple
    normal: tuple
    area: float
    brdf: BRDF = field(default_factory=Lambertian)
    hidden: bool = False
    name: str = ""

    def __post_init__(self):
        c = np.asarray(self.centre, dtype=float)
        n = np.asarray(self.normal, dtype=float)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise SceneError(f"Patch {self.name or ''} centre must be 3 finite numbers (metres); got {self.centre!r}.")
        if n.shape != (3,) or not np.all(np.isfinite(n)):
            raise SceneError(f"Patch {self.name or ''} normal must be 3 finite numbers; got {self.normal!r}.")
        nn = float(np.linalg.norm(n))
        if abs(nn - 1.0) > _UNIT_TOL:
            raise SceneError(f"Patch {self.name or ''} normal must be a unit vector (|n| = 1 within "
                             f"{_UNIT_TOL}); got |n| = {nn:.6g} for {n.tolist()}. Divide it by its norm.")
        try:
            a = float(self.area)
        except (TypeError, ValueError) as exc:
            raise SceneError(f"Patch area must be a number in m^2; got {self.area!r}.") from exc
        if not (a > 0) or not math.isfinite(a):
            raise SceneError(f"Patch {self.name or ''} area must be > 0 m^2 and finite; got {self.area!r}.")
        if not isinstance(self.brdf, (Lambertian, Phong, Mirror)):
            raise SceneError(f"Patch brdf must be Lambertian, Phong or Mirror; got {type(self.brdf).__name__}.")
        object.__setattr__(self, "centre", tuple(c.tolist()))
        object.__setattr__(self, "normal", tuple(n.tolist()))
        object.__setattr__(self, "area", a)


class Scene:
    """M patches, a source and a camera (co-located at the origin by default).

    Parameters
    ----------
    patches : list of Patch.
    source : (3,) position of the pulsed source (metres).
    camera : (3,) position of the detector; defaults to the source (co-located, "patch 0").
    occluders : optional trimesh.Trimesh of extra geometry that blocks light but does not
        reflect (its surfaces are not patches).
    self_occlusion : also test the patches' own surfaces as blockers (mesh scenes).
    phi : pulse energy (default 1).
    """

    def __init__(self, patches, source=(0.0, 0.0, 0.0), camera=None, occluders=None,
                 self_occlusion: bool = False, phi: float = 1.0, name: str = "scene"):
        patches = list(patches)
        if not patches:
            raise SceneError("A Scene needs at least one Patch; got none.")
        for k, p in enumerate(patches):
            if not isinstance(p, Patch):
                raise SceneError(f"Scene patches must be Patch objects; item {k} is {type(p).__name__}.")
        self.patches = tuple(patches)
        self.source = self._point("source", source)
        self.camera = self.source.copy() if camera is None else self._point("camera", camera)
        if occluders is not None and not hasattr(occluders, "ray"):
            raise SceneError("occluders must be a trimesh.Trimesh (got "
                             f"{type(occluders).__name__}); load one with trimesh.load(path).")
        self.occluders = occluders
        self.self_occlusion = bool(self_occlusion)
        if not (float(phi) > 0 and math.isfinite(float(phi))):
            raise SceneError(f"phi (pulse energy) must be > 0 and finite; got {phi!r}.")
        self.phi = float(phi)
        self.name = name
        d = np.linalg.norm(self.positions[:, None] - self.positions[None], axis=-1)
        np.fill_diagonal(d, np.inf)
        if np.min(d) < 1e-9:
            i, j = np.unravel_index(np.argmin(d), d.shape)
            raise SceneError(f"Patches {i} and {j} share the same centre {self.positions[i].tolist()}; "
                             "every patch needs its own position.")
        for nm, pt in (("source", self.source), ("camera", self.camera)):
            dd = np.linalg.norm(self.positions - pt, axis=1)
            if np.min(dd) < 1e-9:
                raise SceneError(f"The {nm} sits on patch {int(np.argmin(dd))}; move it off the surface.")

    @staticmethod
    def _point(name, p) -> np.ndarray:
        a = np.asarray(p, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise SceneError(f"{name} must be 3 finite numbers (metres); got {p!r}.")
        return a

    # ------------------------------------------------------------------ arrays
    @property
    def n_patches(self) -> int:
        return len(self.patches)

    @cached_property
    def positions(self) -> np.ndarray:
        return np.array([p.centre for p in self.patches], dtype=float)

    @cached_property
    def normals(self) -> np.ndarray:
        return np.array([p.normal for p in self.patches], dtype=float)

    @cached_property
    def areas(self) -> np.ndarray:
        return np.array([p.area for p in self.patches], dtype=float)

    @property
    def brdfs(self) -> tuple:
        return tuple(p.brdf for p in self.patches)

    @cached_property
    def distances(self) -> np.ndarray:
        """Patch-to-patch distance matrix (M, M), metres."""
        return np.linalg.norm(self.positions[:, None] - self.positions[None], axis=-1)

    @property
    def source_distances(self) -> np.ndarray:
        return np.linalg.norm(self.positions - self.source, axis=1)

    @property
    def camera_distances(self) -> np.ndarray:
        return np.linalg.norm(self.positions - self.camera, axis=1)

    @property
    def is_glossy(self) -> bool:
        """Whether any patch needs direction-dependent (glossy/mirror) transport."""
        return any(b.glossy for b in self.brdfs)

    @property
    def has_mirrors(self) -> bool:
        return any(isinstance(b, Mirror) for b in self.brdfs)

    @property
    def needs_occlusion(self) -> bool:
        """Whether ray casting is needed (only when the scene has blockers)."""
        return self.occluders is not None or self.self_occlusion

    @cached_property
    def albedos(self) -> np.ndarray:
        return np.array([b.diffuse_albedo for b in self.brdfs])

    # ------------------------------------------------------------------ visibility
    @cached_property
    def _blocker(self):
        import trimesh

        meshes = []
        if self.occluders is not None:
            meshes.append(self.occluders)
        if self.self_occlusion:
            meshes.append(self.patch_mesh())
        return trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]

    def segments_clear(self, a: np.ndarray, b: np.ndarray, eps: float = 1e-6) -> np.ndarray:
        """For segments a[k] -> b[k], True where no blocker triangle lies strictly between.

        Uses trimesh ray casting; only call when ``needs_occlusion``.
        """
        a = np.atleast_2d(np.asarray(a, float))
        b = np.atleast_2d(np.asarray(b, float))
        if not self.needs_occlusion:
            return np.ones(len(a), dtype=bool)
        vec = b - a
        length = np.linalg.norm(vec, axis=1)
        dirs = vec / length[:, None]
        origins = a + dirs * eps * 10
        mesh = self._blocker
        locs, idx_ray, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
        clear = np.ones(len(a), dtype=bool)
        if len(idx_ray):
            hit_d = np.linalg.norm(locs - origins[idx_ray], axis=1)
            remaining = length[idx_ray] - 10 * eps       # from the offset origin to b
            # a hit within the tolerance of b is b's own surface (self-occlusion), not a blocker
            bad = idx_ray[hit_d < remaining - max(self._end_tol(), 20 * eps)]
            clear[np.unique(bad)] = False
        return clear

    def _end_tol(self) -> float:
        return 1e-6 + 1e-3 * float(np.sqrt(np.min(self.areas)))

    @cached_property
    def patch_visibility(self) -> np.ndarray:
        """(M, M) bool: leg k -> i exists (facing each other and unoccluded); diagonal False."""
        z = self.positions
        vis = facing_matrix(z, self.normals)
        if self.needs_occlusion:
            kk, ii = np.nonzero(np.triu(vis, 1))
            if len(kk):
                clear = self.segments_clear(z[kk], z[ii])
                vis[kk[~clear], ii[~clear]] = False
                vis[ii[~clear], kk[~clear]] = False
        return vis

    def _sees(self, point: np.ndarray) -> np.ndarray:
        z, n = self.positions, self.normals
        facing = np.einsum("md,md->m", point[None, :] - z, n) > 0
        declared = np.array([not p.hidden for p in self.patches])
        ok = facing & declared
        if self.needs_occlusion and np.any(ok):
            idx = np.flatnonzero(ok)
            clear = self.segments_clear(z[idx], np.repeat(point[None], len(idx), axis=0))
            ok[idx[~clear]] = False
        return ok

    @cached_property
    def visible(self) -> np.ndarray:
        """(M,) bool: patch j is seen by the camera (a column of the STIR)."""
        return self._sees(self.camera)

    @cached_property
    def illuminable(self) -> np.ndarray:
        """(M,) bool: the source can aim its pulse at patch i (a row of the STIR)."""
        return self._sees(self.source)

    @property
    def hidden(self) -> np.ndarray:
        """(M,) bool: neither seen by the camera nor reached by the source."""
        return ~(self.visible | self.illuminable)

    @property
    def illuminated_ids(self) -> np.ndarray:
        return np.flatnonzero(self.illuminable)

    @property
    def observed_ids(self) -> np.ndarray:
        return np.flatnonzero(self.visible)

    # ------------------------------------------------------------------ checks
    def form_factor_row_sums(self) -> np.ndarray:
        """For each patch k, sum_i a_i cos_k cos_i v / (pi d^2): the fraction of its diffuse
        emission that lands on other patches (must be <= 1 for energy conservation)."""
        from .radiometry import cosines, form_factor

        z, n, a = self.positions, self.normals, self.areas
        vec = z[None, :, :] - z[:, None, :]
        d = self.distances.copy()
        np.fill_diagonal(d, 1.0)
        ck, ci = cosines(vec, n[:, None, :], n[None, :, :], d)
        g = form_factor(a[None, :], ci, ck, d) * self.patch_visibility  # a_i cos cos / d^2
        return g.sum(axis=1) / math.pi

    def check_physics(self, warn: bool = True) -> dict:
        """Warn when the small-patch approximation would create energy; return the figures."""
        rs = self.form_factor_row_sums()
        bad = np.flatnonzero(rs > 1.0)
        if warn and len(bad):
            warnings.warn(f"Form-factor row sums exceed 1 for patches {bad.tolist()[:10]} (max "
                          f"{rs.max():.3g}): patches are too large for their distances and the "
                          "small-patch approximation creates energy. Subdivide them.",
                          PhysicsWarning, stacklevel=2)
        return {"max_form_factor_row_sum": float(rs.max()), "patches_over_one": bad.tolist()}

    # ------------------------------------------------------------------ meshes
    def patch_mesh(self):
        """A trimesh of the patches as squares of their area (for occlusion and pictures)."""
        import trimesh

        verts, faces = [], []
        for k, p in enumerate(self.patches):
            c, n = np.asarray(p.centre), np.asarray(p.normal)
            t = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
            t /= np.linalg.norm(t)
            b = np.cross(n, t)
            h = 0.5 * math.sqrt(p.area)
            q = [c + h * (sx * t + sy * b) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            base = 4 * k
            verts.extend(q)
            faces.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])
        return trimesh.Trimesh(np.array(verts), np.array(faces), process=False)

    @classmethod
    def from_mesh(cls, mesh, patch_size: float, brdf: BRDF | None = None, source=(0, 0, 0),
                  camera=None, self_occlusion: bool = True, occluders=None,
                  name: str | None = None) -> "Scene":
        """Split a triangle mesh (path to OBJ/PLY/STL, or a trimesh.Trimesh) into patches.

        Triangles are subdivided until every edge is at most ``patch_size`` metres; each
        resulting triangle becomes one patch (centroid, face normal, area). The mesh itself is
        used as the occluder when ``self_occlusion`` is True.
        """
        import trimesh

        if not (patch_size > 0):
            raise SceneError(f"patch_size must be > 0 metres; got {patch_size!r}.")
        label = name
        if isinstance(mesh, (str, Path)):
            path = Path(mesh)
            if not path.exists():
                raise SceneError(f"Mesh file not found: {path}.")
            try:
                mesh = trimesh.load(path, force="mesh")
            except Exception as exc:
                raise SceneError(f"Could not read mesh {path} ({exc}); supported: OBJ, PLY, STL.") from exc
            label = label or path.stem
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            raise SceneError("from_mesh needs a triangle mesh with at least one face.")
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=patch_size,
                                                max_iter=20)
        sub = trimesh.Trimesh(v, f, process=False)
        keep = sub.area_faces > 1e-14
        brdf = brdf or Lambertian()
        patches = [Patch(centre=c, normal=n / np.linalg.norm(n), area=a, brdf=brdf)
                   for c, n, a in zip(sub.triangles_center[keep], sub.face_normals[keep],
                                      sub.area_faces[keep])]
        scene = cls(patches, source=source, camera=camera, occluders=occluders,
                    self_occlusion=False, name=label or "mesh")
        if self_occlusion:
            scene.self_occlusion = True
            scene.__dict__["_blocker"] = mesh if occluders is None else trimesh.util.concatenate([mesh, occluders])
        return scene

    def describe(self) -> str:
        kinds = sorted({b.kind for b in self.brdfs})
        return (f"Scene '{self.name}': {self.n_patches} patches ({', '.join(kinds)}), "
                f"{int(self.visible.sum())} visible, {int(self.hidden.sum())} hidden, "
                f"occluders={'yes' if self.needs_occlusion else 'no'}")

    def truth_dict(self) -> dict:
        """The scene as the Capture file's ``truth/`` group."""
        kinds = {b.kind for b in self.brdfs}
        brdf = kinds.pop() if len(kinds) == 1 else "mixed"
        out = {"positions": self.positions, "normals": self.normals, "areas": self.areas,
               "albedo": self.albedos, "visible": self.visible, "brdf": brdf}
        if any(isinstance(b, Phong) for b in self.brdfs):
            out["specular"] = np.array([getattr(b, "specular", 0.0) for b in self.brdfs])
            out["exponent"] = np.array([getattr(b, "exponent", 0.0) for b in self.brdfs])
        return out
