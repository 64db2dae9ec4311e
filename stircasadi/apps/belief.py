"""What the estimate says about the scene: a Scene at the estimate, its parameters and covariance.

When to use
-----------
Every application that renders from an estimate (relighting from a new source or viewpoint,
material replacement, segmentation) starts here: ``SceneBelief.from_estimate(d)`` parses the
estimate.json structure (schema v2, ``docs/estimate-json.md``) into

* ``scene``: a ``stircasadi.scene.Scene`` at the estimated values (the estimate's source and
  camera, every patch it reports);
* ``names`` / ``values``: the parameter vector, named as the schema names covariance entries
  (``position[ID].x``, ``normal[ID].y``, ``area[ID]``, ``albedo[ID]``, ``albedo_area[ID]``,
  ``specular[ID]``, ``exponent[ID]``);
* ``covariance``: the estimate's joint ``covariance`` block where it names a parameter, and the
  per-number ``<name>_std`` squared on the diagonal elsewhere (cross-covariances between a
  parameter in the joint block and one outside it are taken as zero: the schema reports none);
* ``scene_at(theta, source=..., camera=...)``: the Scene rebuilt from a parameter vector (normals
  renormalised), the map the uncertainty propagation differentiates.

What cannot be rendered is refused (``EstimateInputError``), each patch and value named:

* a patch whose ``position`` or ``normal`` is null: no light path through it has a length;
* a visible patch whose ``area`` is null (and no declared area): the pulse's irradiance
  ``phi / a`` and its emission toward other patches need the area;
* an estimate whose verdict is UNRELIABLE (``success`` false), unless ``allow_unreliable``.

Hidden patches known only through ``albedo_area`` (albedo x area)
------------------------------------------------------------------
For a Lambertian patch h every visit of a light path *through* h (neither aimed at by the source
nor read by the camera) multiplies the path by ``rho_h / pi`` on arrival and by ``a_h`` in the
form factor of the next leg: the path depends on h only through ``rho_h a_h``. Such a patch is
rendered exactly with a proxy (albedo ``PROXY_ALBEDO``, area ``albedo_area / PROXY_ALBEDO``)
*as long as it stays a pass-through patch*. A configuration in which the camera would see it or
the source aim at it needs ``rho_h`` and ``a_h`` separately and is refused by the renderers
(``SceneBelief.check_renderable``), naming the patch and the fix (declare its area with
``areas={id: a}``). Proxy patches are declared hidden in ``scene`` so the transport never
illuminates or reads them.

Neglected: cross-covariances the estimate does not report; the shape of the estimate's error
beyond its covariance (a Gaussian belief).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..brdf import Lambertian, Phong
from ..errors import BRDFError, EstimateInputError, SceneError
from ..scene import Patch, Scene

__all__ = ["SceneBelief", "PROXY_ALBEDO", "parse_name", "param_name"]

#: albedo given to a hidden patch known only through albedo x area (its area is then
#: albedo_area / PROXY_ALBEDO); any value in (0, 1] renders pass-through paths identically
PROXY_ALBEDO = 0.5
_AXES = "xyz"
_NAME = re.compile(r"^([a-z_]+)\[(-?\d+)\](?:\.([xyz]))?$")


def param_name(kind: str, pid: int, axis: int | None = None) -> str:
    """The schema's name of a parameter: ``albedo[3]``, ``position[5].x``."""
    return f"{kind}[{int(pid)}]" + ("" if axis is None else f".{_AXES[axis]}")


def parse_name(name: str) -> tuple[str, int, int | None]:
    """``"position[5].x"`` -> ``("position", 5, 0)``; raises EstimateInputError otherwise."""
    m = _NAME.match(str(name))
    if not m:
        raise EstimateInputError(f"Covariance parameter name {name!r} is not of the form kind[ID] or "
                                 "kind[ID].x (docs/estimate-json.md), e.g. 'albedo[3]', 'position[5].x'.")
    return m.group(1), int(m.group(2)), (None if m.group(3) is None else _AXES.index(m.group(3)))


def _number(v) -> float | None:
    if v is None:
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _vector(v, n=3) -> list | None:
    if v is None or not isinstance(v, (list, tuple)) or len(v) != n:
        return None
    out = [_number(x) for x in v]
    return out


@dataclass
class SceneBelief:
    """A Gaussian belief about a scene: the estimate and its covariance (see the module doc).

    Build with :meth:`from_estimate`. Attributes are read-only by convention.
    """

    scene: Scene
    ids: np.ndarray                      # estimate patch id of scene.patches[k]
    names: list                          # parameter names
    values: np.ndarray                   # parameter vector at the estimate
    covariance: np.ndarray               # (P, P)
    visible: np.ndarray                  # (M,) the estimate's `visible` flags
    proxy_ids: tuple = ()                # hidden patches rendered through albedo_area only
    missing_std: list = field(default_factory=list)   # parameters reported without a std
    notes: list = field(default_factory=list)
    frame: str = "capture"
    verdict: str = "OK"
    kinds: list = field(default_factory=list)        # "lambertian" | "phong" per patch
    labels: list = field(default_factory=list)       # patch names
    _slots: dict = field(default_factory=dict, repr=False)   # (kind, pid) -> indices

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_estimate(cls, estimate: dict, areas: dict | None = None,
                      allow_unreliable: bool = False, exclude=()) -> "SceneBelief":
        """Parse an estimate.json dict (schema v2).

        Parameters
        ----------
        estimate : the dict (``EstimateResult.to_json_dict()`` or ``json.load``).
        areas : optional ``{patch id: area m^2}`` declared for patches whose ``area`` is null or
            missing (an input, std 0); estimated areas are kept.
        allow_unreliable : render an estimate whose verdict is UNRELIABLE (the belief's
            ``verdict`` then says so and every result carries it).
        exclude : patch ids left out of the scene (e.g. a patch the data cannot place); their
            light is then missing from every render.
        """
        if not isinstance(estimate, dict):
            raise EstimateInputError(f"An estimate must be the estimate.json object (a dict); got "
                                     f"{type(estimate).__name__}.")
        fmt, ver = estimate.get("format"), estimate.get("version")
        if fmt not in (None, "stircasadi.estimate") or ver not in (None, 2):
            raise EstimateInputError(f"Expected an estimate with format 'stircasadi.estimate' and "
                                     f"version 2; got format={fmt!r}, version={ver!r}.")
        verdict = "OK" if estimate.get("success", False) else "UNRELIABLE"
        if verdict != "OK" and not allow_unreliable:
            reasons = estimate.get("reasons") or ["success is false"]
            raise EstimateInputError(
                "The estimate's verdict is UNRELIABLE (" + "; ".join(map(str, reasons))[:400] +
                "): rendering from it would present unverified numbers as results. Fix the capture "
                "or the estimate, or pass allow_unreliable=True (--allow-unreliable) to render "
                "anyway with every result marked UNRELIABLE.")
        patches = estimate.get("patches")
        if not isinstance(patches, list) or not patches:
            raise EstimateInputError("The estimate has no 'patches' list; nothing to render.")
        areas = {int(k): float(v) for k, v in (areas or {}).items()}
        exclude = {int(x) for x in exclude}
        known_ids = [p.get("id") for p in patches if isinstance(p, dict)]
        for k in list(areas) + sorted(exclude):
            if k not in known_ids:
                raise EstimateInputError(f"Patch id {k} (in areas/exclude) is not in the estimate; its "
                                         f"ids are {known_ids[:30]}.")
        problems, built = [], []
        names, vals, stds, notes, missing = [], [], [], [], []
        slots: dict = {}
        proxy = []
        for p in patches:
            pid = p.get("id")
            if pid in exclude:
                notes.append(f"patch {pid} excluded by request: its light is missing from renders")
                continue
            rec = _patch_record(p, areas, problems)
            if rec is None:
                continue
            built.append(rec)
            if rec["proxy"]:
                proxy.append(rec["id"])
            for kind, v, s, src in rec["params"]:
                idx = []
                for a, (vv, ss) in enumerate(zip(np.atleast_1d(v), np.atleast_1d(s))):
                    nm = param_name(kind, rec["id"], a if np.ndim(v) else None)
                    idx.append(len(names))
                    names.append(nm)
                    vals.append(vv)
                    if ss is None:
                        missing.append(nm)
                        ss = 0.0
                    stds.append(float(ss))
                slots[(kind, rec["id"])] = np.array(idx)
                if src:
                    notes.append(f"patch {rec['id']}: {kind} {src}")
        if problems:
            raise EstimateInputError("The estimate cannot be rendered:\n  - " + "\n  - ".join(problems))
        values = np.array(vals, float)
        cov = np.diag(np.square(stds))
        cov_in = estimate.get("covariance")
        if cov_in:
            _merge_covariance(cov, names, cov_in, missing, notes)
        declared = [slots[("area", r["id"])][0] for r in built if r["declared_area"]]
        cov[declared, :] = 0.0   # a declared input is exact, whatever the joint block said
        cov[:, declared] = 0.0
        src = _number_vec(estimate.get("source_xyz"))
        cam = _number_vec(estimate.get("camera_xyz"))
        frame = estimate.get("frame", "capture")
        if src is None:
            if frame != "source-origin":
                raise EstimateInputError("The estimate's source_xyz is missing or null and its frame is "
                                         f"{frame!r}; the renderers need the source position "
                                         "(give source= explicitly).")
            src = np.zeros(3)
        belief = cls(scene=None, ids=np.array([r["id"] for r in built], int), names=names,
                     values=values, covariance=cov,
                     visible=np.array([r["visible"] for r in built], bool),
                     proxy_ids=tuple(proxy), missing_std=missing, notes=notes, frame=frame,
                     verdict=verdict, kinds=[r["kind"] for r in built],
                     labels=[r["name"] for r in built], _slots=slots)
        belief.scene = belief.scene_at(values, source=src, camera=cam if cam is not None else src)
        return belief

    # ------------------------------------------------------------------ parameter map
    @property
    def n_params(self) -> int:
        return len(self.values)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def index(self, patch_id: int) -> int:
        """Position in ``scene.patches`` of the patch with estimate id ``patch_id``."""
        hit = np.flatnonzero(self.ids == int(patch_id))
        if not hit.size:
            raise SceneError(f"Unknown patch id {patch_id}; the estimate's patches are {self.ids.tolist()[:30]}.")
        return int(hit[0])

    def slot(self, kind: str, patch_id: int) -> np.ndarray | None:
        """Indices of parameter ``kind`` of patch ``patch_id`` in the vector (None if absent)."""
        return self._slots.get((kind, int(patch_id)))

    def scene_at(self, theta, source=None, camera=None, brdf_override: dict | None = None) -> Scene:
        """The Scene at parameter vector ``theta`` (source/camera default to the belief's).

        ``brdf_override`` maps patch ids to a BRDF that replaces the estimated one (material
        replacement); a replaced patch's BRDF parameters in ``theta`` are then ignored.
        """
        theta = np.asarray(theta, float)
        if theta.shape != self.values.shape:
            raise EstimateInputError(f"theta must have {self.n_params} parameters; got {theta.shape}.")
        brdf_override = brdf_override or {}
        pts = []
        for k, pid in enumerate(self.ids):
            pid = int(pid)
            g = lambda kind: theta[self._slots[(kind, pid)]]  # noqa: E731
            c = g("position")
            n = g("normal")
            nn = float(np.linalg.norm(n))
            if not nn > 0:
                raise EstimateInputError(f"patch {pid}: the normal is the zero vector.")
            n = n / nn
            if pid in self.proxy_ids:
                aa = float(g("albedo_area")[0])
                area, albedo = max(aa, 1e-300) / PROXY_ALBEDO, PROXY_ALBEDO
            else:
                area, albedo = float(g("area")[0]), float(g("albedo")[0])
            if pid in brdf_override:
                brdf = brdf_override[pid]
            else:
                try:
                    if self.kinds[k] == "phong":
                        brdf = Phong(albedo, float(g("specular")[0]), float(g("exponent")[0]))
                    else:
                        brdf = Lambertian(albedo)
                except BRDFError as exc:
                    raise EstimateInputError(f"patch {pid}: {exc}") from exc
            try:
                pts.append(Patch(tuple(c), tuple(n), area, brdf, hidden=pid in self.proxy_ids,
                                 name=self.labels[k]))
            except SceneError as exc:
                raise EstimateInputError(f"patch {pid}: {exc}") from exc
        src = self.scene.source if source is None else source
        cam = (self.scene.camera if self.scene is not None else src) if camera is None else camera
        return Scene(pts, source=src, camera=cam, name="estimate")

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` parameter vectors from N(values, covariance) (rows)."""
        L = _psd_factor(self.covariance)
        return self.values[None, :] + rng.standard_normal((n, L.shape[1])) @ L.T

    def check_renderable(self, scene: Scene, illuminated_ids=None) -> None:
        """Refuse a configuration in which a proxy (albedo x area only) patch would be read by the
        camera or aimed at by the source (see the module docstring)."""
        if not self.proxy_ids:
            return
        geo = Scene([Patch(p.centre, p.normal, p.area, p.brdf, hidden=False, name=p.name)
                     for p in scene.patches], source=scene.source, camera=scene.camera)
        for pid in self.proxy_ids:
            k = self.index(pid)
            if geo.visible[k]:
                raise EstimateInputError(
                    f"Patch {pid} ({self.labels[k]}) is known only through albedo x area = "
                    f"{self.values[self._slots[('albedo_area', pid)]][0]:.4g} m^2, and the camera at "
                    f"{np.round(scene.camera, 4).tolist()} would see it directly: its radiance needs "
                    f"the albedo alone. Declare its area (areas={{{pid}: A}}, --area {pid}=A) or keep "
                    "the camera where it cannot see that patch.")
            if illuminated_ids is not None and pid in set(int(i) for i in illuminated_ids):
                raise EstimateInputError(
                    f"Patch {pid} ({self.labels[k]}) is known only through albedo x area; aiming the "
                    "pulse at it needs its area (irradiance phi / a). Declare its area "
                    f"(areas={{{pid}: A}}) or leave it out of the illumination.")


# ---------------------------------------------------------------------- helpers
def _number_vec(v):
    vec = _vector(v)
    if vec is None or any(x is None for x in vec):
        return None
    return np.array(vec, float)


def _std_vec(p, key, n):
    s = p.get(key)
    if s is None:
        return [None] * n if n > 1 else None
    if n == 1:
        v = _number(s)
        return None if v is None else abs(v)
    vec = _vector(s, n)
    if vec is None:
        return [None] * n
    return [None if x is None else abs(x) for x in vec]


def _patch_record(p: dict, areas: dict, problems: list) -> dict | None:
    """One patch's values, stds and BRDF kind; appends what is wrong to ``problems``."""
    if not isinstance(p, dict) or "id" not in p:
        problems.append(f"a patch entry is not an object with an 'id': {str(p)[:80]}")
        return None
    pid = int(p["id"])
    name = str(p.get("name") or (f"V{pid}" if p.get("visible", True) else f"H{pid}"))
    visible = bool(p.get("visible", True))
    notes = p.get("notes") or {}
    why = lambda k: f" ({notes[k]})" if isinstance(notes, dict) and k in notes else ""  # noqa: E731
    start = len(problems)
    pos, nrm = _vector(p.get("position")), _vector(p.get("normal"))
    if pos is None or any(x is None for x in pos):
        problems.append(f"patch {pid} ({name}): position is null{why('position')}; every light path "
                        f"through it needs its place. Give its position, or exclude it (exclude=[{pid}], "
                        f"--exclude {pid}) and accept that its light is missing.")
    if nrm is None or any(x is None for x in nrm):
        problems.append(f"patch {pid} ({name}): normal is null{why('normal')}; its cosines need it. "
                        f"Give its normal, or exclude it (exclude=[{pid}]).")
    params = []
    area, albedo, aa = _number(p.get("area")), _number(p.get("albedo")), _number(p.get("albedo_area"))
    proxy = False
    src_area = None
    if area is None and pid in areas:
        area, src_area = areas[pid], "declared by the caller (std 0)"
    if area is not None and area <= 0:
        problems.append(f"patch {pid} ({name}): area must be > 0 m^2; got {area}.")
    if area is None or albedo is None:
        if not visible and aa is not None and aa > 0:
            proxy = True
        else:
            miss = "area" if area is None else "albedo"
            fix = (f"declare it with areas={{{pid}: A}} (--area {pid}=A)" if miss == "area"
                   else "the estimate must report it (run the reflectance stage)")
            problems.append(f"patch {pid} ({name}): {miss} is null{why(miss)}; rendering needs it "
                            f"(the pulse's irradiance phi/a and the patch's emission scale with the "
                            f"area, its reflection with the albedo). Fix: {fix}, or exclude it "
                            f"(exclude=[{pid}]).")
    spec, expo = _number(p.get("specular")), _number(p.get("exponent"))
    kind = "lambertian"
    if spec is not None or expo is not None:
        if spec is None or expo is None:
            problems.append(f"patch {pid} ({name}): a Phong patch needs both specular and exponent; "
                            f"got specular={spec}, exponent={expo}.")
        elif proxy:
            problems.append(f"patch {pid} ({name}): a glossy patch known only through albedo x area "
                            "cannot be rendered (its lobe scales differently); declare its area.")
        else:
            kind = "phong"
    if len(problems) > start:
        return None
    params.append(("position", np.array(pos), _std_vec(p, "position_std", 3), None))
    params.append(("normal", np.array(nrm) / np.linalg.norm(nrm), _std_vec(p, "normal_std", 3), None))
    if proxy:
        params.append(("albedo_area", aa, _std_vec(p, "albedo_area_std", 1),
                       f"known only as albedo x area (proxy albedo {PROXY_ALBEDO})"))
    else:
        params.append(("area", area, 0.0 if src_area else _std_vec(p, "area_std", 1), src_area))
        params.append(("albedo", albedo, _std_vec(p, "albedo_std", 1), None))
    if kind == "phong":
        params.append(("specular", spec, _std_vec(p, "specular_std", 1), None))
        params.append(("exponent", expo, _std_vec(p, "exponent_std", 1), None))
    return {"id": pid, "name": name, "visible": visible, "kind": kind, "proxy": proxy,
            "params": params, "declared_area": src_area is not None}


def _merge_covariance(cov, names, cov_in, missing, notes) -> None:
    """Write the estimate's joint covariance block over the diagonal built from the stds."""
    if not isinstance(cov_in, dict) or "parameters" not in cov_in or "matrix" not in cov_in:
        raise EstimateInputError("The estimate's 'covariance' must be {'parameters': [...], "
                                 "'matrix': [[...]]} (docs/estimate-json.md).")
    pn = [str(x) for x in cov_in["parameters"]]
    try:
        C = np.array(cov_in["matrix"], dtype=float)
    except (TypeError, ValueError) as exc:
        raise EstimateInputError("The estimate's covariance matrix must hold numbers (no nulls).") from exc
    if C.shape != (len(pn), len(pn)):
        raise EstimateInputError(f"The covariance matrix must be {len(pn)} x {len(pn)} to match its "
                                 f"parameter names; got {C.shape}.")
    if len(set(pn)) != len(pn):
        raise EstimateInputError("The covariance names a parameter twice.")
    if not np.all(np.isfinite(C)):
        raise EstimateInputError("The covariance matrix holds NaN or inf.")
    if np.max(np.abs(C - C.T)) > 1e-9 * max(np.max(np.abs(C)), 1e-300):
        raise EstimateInputError("The covariance matrix is not symmetric.")
    ev = np.linalg.eigvalsh(C) if len(C) else np.zeros(0)
    if len(ev) and ev.min() < -1e-9 * max(ev.max(), 1e-300):
        raise EstimateInputError(f"The covariance matrix is not positive semi-definite (smallest "
                                 f"eigenvalue {ev.min():.3g}).")
    where = {n: k for k, n in enumerate(names)}
    mine, theirs, unused = [], [], []
    for k, n in enumerate(pn):
        parse_name(n)
        if n in where:
            mine.append(where[n])
            theirs.append(k)
        else:
            unused.append(n)
    if unused:
        notes.append(f"covariance entries not rendered (no such parameter here): {unused[:10]}")
    mine, theirs = np.array(mine, int), np.array(theirs, int)
    cov[np.ix_(mine, mine)] = C[np.ix_(theirs, theirs)]
    for k in mine:
        if names[k] in missing:
            missing.remove(names[k])


def _psd_factor(cov: np.ndarray) -> np.ndarray:
    """L with L L^T = cov for a symmetric positive semi-definite matrix (eigen-decomposition)."""
    w, V = np.linalg.eigh(0.5 * (cov + cov.T))
    w = np.clip(w, 0.0, None)
    keep = w > 0
    return V[:, keep] * np.sqrt(w[keep])[None, :]
