"""Force one effect of the forward model on or off against ``simulate``'s automatic choice.

When to use
-----------
The ``effects`` study (factors ``effect`` and ``effect_state``): each cell simulates the scene
as ``simulate`` would by itself (the reference) and with the effect forced, and records what
forcing costs (simulation time) and what it changes (the largest change of the ideal STIR,
relative to its peak and to the noise std) -- DESIGN.md section 7 shown, not asserted.

The switches (``force(scene, sensor, effect, state)``):

=========  ======================================  =======================================
effect     on                                      off
=========  ======================================  =======================================
bounces    ``bounces = needed + 1`` (light after   ``bounces = needed - 1`` (>= 1)
           the grid's end is cut, as a sensor's)
occlusion  the scene's occluders, or a far box     no occluders (every facing pair linked)
           behind the camera (rays cast, none hit)
glossy     every Lambertian patch as Phong with    every Phong patch as Lambertian with
           specular 1e-12 (glossy nodes, the       its diffuse albedo (the lobe dropped)
           light changes by ~1e-12)
irf        the sensor's IRF, or 210 ps Gaussian    the ideal (Dirac) response
noise      the sensor's noise, or 1e-4 of peak     no noise
=========  ======================================  =======================================

What it neglects
----------------
Turning occlusion off can make occluded patches visible, so the two STIRs can differ in shape;
the change is then measured over the (illuminated, observed) ids both share and the note says
how many patches changed. The noise effect changes no ideal STIR: its change is the drawn noise.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..brdf import Lambertian, Phong
from ..errors import StudyError
from ..irf import GaussianIRF, IdealIRF
from ..scene import Patch, Scene
from ..sensor import GaussianNoise
from ..transport import needed_bounces

__all__ = ["force", "stir_change"]

#: the specular reflectance that makes a Lambertian patch glossy for the simulator (which skips
#: lobes of specular 0) while changing its light by a negligible amount
_TINY_LOBE = 1e-12


def _rebuild(scene: Scene, patches=None, occluders="keep") -> Scene:
    return Scene(patches if patches is not None else scene.patches, source=scene.source,
                 camera=scene.camera, occluders=scene.occluders if occluders == "keep" else occluders,
                 self_occlusion=scene.self_occlusion, phi=scene.phi, name=scene.name)


def _far_box(scene: Scene):
    import trimesh

    box = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    box.apply_translation(scene.camera - 5.0 * _forward(scene))
    return box


def _forward(scene: Scene) -> np.ndarray:
    d = scene.positions.mean(axis=0) - scene.camera
    return d / np.linalg.norm(d)


def force(scene: Scene, sensor, effect: str, state: str):
    """(scene, sensor, simulate keyword arguments, note) with ``effect`` forced to ``state``."""
    if state == "auto" or effect == "none":
        return scene, sensor, {}, ""
    on = state == "on"
    if effect == "bounces":
        k = needed_bounces(scene)
        k = k + 1 if on else max(k - 1, 1)
        # the extra order may arrive after the grid's end: the grid records what it can, as a
        # sensor would (the automatic order always fits the problem's grid)
        kw = {"bounces": k, "allow_truncation": True} if on else {"bounces": k}
        return scene, sensor, kw, f"bounces {k} (scene needs {needed_bounces(scene)})"
    if effect == "occlusion":
        if on:
            if scene.needs_occlusion:
                return scene, sensor, {}, "occluders of the scene"
            return _rebuild(scene, occluders=_far_box(scene)), sensor, {}, "a far box: rays cast, none blocked"
        return _rebuild(scene, occluders=None), sensor, {}, "occluders removed"
    if effect == "glossy":
        if on:
            P = [p if isinstance(p.brdf, Phong) or not isinstance(p.brdf, Lambertian) else
                 dataclasses.replace(p, brdf=Phong(albedo=min(p.brdf.albedo, 1 - _TINY_LOBE),
                                                   specular=_TINY_LOBE, exponent=1.0))
                 for p in scene.patches]
            return _rebuild(scene, P), sensor, {}, f"Lambertian patches as Phong with specular {_TINY_LOBE:g}"
        P = [dataclasses.replace(p, brdf=Lambertian(p.brdf.albedo)) if isinstance(p.brdf, Phong) else p
             for p in scene.patches]
        return _rebuild(scene, P), sensor, {}, "Phong lobes dropped"
    if effect == "irf":
        if on:
            irf = sensor.irf if not isinstance(sensor.irf, IdealIRF) else GaussianIRF.from_ps(210.0)
            return scene, dataclasses.replace(sensor, irf=irf), {}, f"irf {irf.describe()}"
        return scene, dataclasses.replace(sensor, irf=IdealIRF()), {}, "ideal impulse response"
    if effect == "noise":
        if on:
            noise = sensor.noise if sensor.noise is not None else GaussianNoise(relative=1e-4)
            return scene, dataclasses.replace(sensor, noise=noise), {}, f"noise {noise}"
        return scene, dataclasses.replace(sensor, noise=None), {}, "no noise"
    raise StudyError(f"Unknown effect {effect!r}.")


def stir_change(ref, forced) -> tuple[float, str]:
    """max |forced - ref| over the (illuminated, observed) ids both transients share, and a note
    when their ids differ."""
    ri, ro = np.asarray(ref.ill_ids), np.asarray(ref.obs_ids)
    fi, fo = np.asarray(forced.ill_ids), np.asarray(forced.obs_ids)
    note = ""
    if not (np.array_equal(ri, fi) and np.array_equal(ro, fo)):
        note = (f"ids differ: illuminated {len(ri)} -> {len(fi)}, observed {len(ro)} -> {len(fo)}; "
                "compared on the shared ones")
    ci, co = np.intersect1d(ri, fi), np.intersect1d(ro, fo)
    if ci.size == 0 or co.size == 0 or ref.stir.shape[-1] != forced.stir.shape[-1]:
        return float("nan"), note or "nothing shared to compare"
    a = ref.stir[np.ix_(np.searchsorted(ri, ci), np.searchsorted(ro, co))]
    b = forced.stir[np.ix_(np.searchsorted(fi, ci), np.searchsorted(fo, co))]
    return float(np.max(np.abs(b - a))), note
