"""Material replacement: give a patch or a segment another BRDF and re-render it.

When to use
-----------
To see what the scene would look like (transient and steady state) if some of its surfaces were
made of another material: paint a wall darker, make a patch glossy, turn a segment found by
``stircasadi.apps.segment`` into a mirror-like Phong lobe. The estimate (``SceneBelief``) is
rendered before and after with the same grid, sensor, source, camera and illumination
(``stircasadi.apps.render``), each with the std propagated from the estimate's covariance (the
new material is exact; every other parameter keeps its uncertainty).

Equation: the replaced patches' BRDF ``f_k`` enters the transport network
(``stircasadi.transport.system``) in place of the estimated one; nothing else changes. A new BRDF
must conserve energy (Lambertian albedo <= 1; Phong ``albedo + specular <= 1``, its
directional-hemispherical albedo): one that would create energy is refused.

Neglects: what the estimate neglects; a patch known only through albedo x area cannot be given a
new material (its area is unknown) and is refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..brdf import BRDF, Lambertian, Mirror, Phong, brdf_from_params
from ..errors import BRDFError, EstimateInputError, SceneError
from .belief import SceneBelief
from .render import RenderSettings, Rendering, render

__all__ = ["Replacement", "make_brdf", "replace_material", "target_ids"]


@dataclass
class Replacement:
    """Before/after renders of a material replacement (ids are estimate ids)."""

    ids: np.ndarray
    brdf: BRDF
    before: Rendering
    after: Rendering


def make_brdf(kind: str, albedo: float | None = None, specular: float | None = None,
              exponent: float | None = None) -> BRDF:
    """A replacement BRDF by name, refusing one that creates energy (say which sum and how)."""
    if kind == "lambertian":
        params = {"albedo": albedo}
    elif kind == "phong":
        params = {"albedo": albedo, "specular": specular, "exponent": exponent}
    else:
        raise BRDFError(f"A replacement material is 'lambertian' or 'phong'; got {kind!r}.")
    missing = [k for k, v in params.items() if v is None]
    if missing:
        raise BRDFError(f"A {kind} material needs {', '.join(params)}; missing {missing}.")
    if kind == "phong" and params["albedo"] + params["specular"] > 1.0 + 1e-12:
        raise BRDFError(f"The replacement material creates energy: albedo + specular = "
                        f"{params['albedo']} + {params['specular']} = "
                        f"{params['albedo'] + params['specular']:.4g} > 1 (its hemispherical albedo "
                        "would exceed 1, reflecting more light than arrives). Lower one so the sum is <= 1.")
    try:
        return brdf_from_params(kind, **params)
    except BRDFError as exc:
        raise BRDFError(f"The replacement material is not physical: {exc}") from exc


def target_ids(belief: SceneBelief, ids=None, segmentation=None, material: int | None = None) -> np.ndarray:
    """The patch ids to replace: explicit ``ids``, or every patch of ``material`` in a
    ``Segmentation``; unknown ids and materials are refused with the known ones."""
    if (ids is None) == (material is None):
        raise SceneError("Name the patches to replace: give ids, or a segmentation and a material "
                         "index (not both, not neither).")
    if material is not None:
        if segmentation is None:
            raise SceneError("A material index needs the segmentation it refers to.")
        if not (0 <= int(material) < segmentation.n_materials):
            raise SceneError(f"Unknown material {material}; the segmentation has materials "
                             f"0..{segmentation.n_materials - 1}.")
        ids = segmentation.materials[int(material)]["ids"]
    ids = np.atleast_1d(np.asarray(ids, int))
    known = set(int(v) for v in belief.ids)
    unknown = [int(v) for v in ids if int(v) not in known]
    if unknown:
        raise SceneError(f"Unknown patch id(s) {unknown}; the estimate's patches are {sorted(known)[:30]}.")
    if len(set(ids.tolist())) != len(ids):
        raise SceneError(f"A patch is named twice: {ids.tolist()}.")
    proxy = [int(v) for v in ids if int(v) in belief.proxy_ids]
    if proxy:
        raise EstimateInputError(f"Patch(es) {proxy} are known only through albedo x area: a new material "
                                 "needs their area. Declare it (areas={id: A}, --area ID=A).")
    return ids


def replace_material(belief: SceneBelief, brdf: BRDF, ids=None, segmentation=None,
                     material: int | None = None, grid=None, sensor=None, source=None, camera=None,
                     illumination=None, settings: RenderSettings | None = None) -> Replacement:
    """Render the estimate before and after giving patches ``ids`` (or a segmentation's
    ``material``) the BRDF ``brdf``; same configuration for both (``stircasadi.apps.render``)."""
    if not isinstance(brdf, (Lambertian, Phong, Mirror)):
        raise BRDFError(f"brdf must be a Lambertian, Phong or Mirror object; got {type(brdf).__name__}.")
    ids = target_ids(belief, ids, segmentation, material)
    settings = settings or RenderSettings()
    before = render(belief, grid=grid, sensor=sensor, source=source, camera=camera,
                    illumination=illumination, settings=settings)
    after = render(belief, grid=before.grid, sensor=sensor, source=source, camera=camera,
                   illumination=illumination, settings=settings,
                   brdf_override={int(i): brdf for i in ids})
    return Replacement(ids=ids, brdf=brdf, before=before, after=after)
