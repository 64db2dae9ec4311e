"""Estimates of known scenes: the twin experiments' estimate.json dicts.

When to use
-----------
Tests, benchmarks and notebooks of the applications need an estimate whose truth is known, with
a covariance that is exactly the error it was drawn with, so that what an application propagates
(relighting std, segmentation tests) can be checked for coverage without depending on the
estimator's internals. ``estimate_from_scene(scene, std, rng)`` writes the estimate.json
structure (schema v2, docs/estimate-json.md) for a ``Scene``: the truth, or one draw from
N(truth, covariance) when a seeded generator is given.

Neglects: the estimator's own errors (biases, non-Gaussian tails): this is a model of an estimate.
"""
from __future__ import annotations

import numpy as np

from ..brdf import Phong
from ..errors import EstimateInputError
from ..scene import Scene
from .belief import _psd_factor, param_name

__all__ = ["estimate_from_scene"]

_STD_KEYS = ("position", "normal", "area", "albedo", "specular", "exponent")


def estimate_from_scene(scene: Scene, std: dict, rng: np.random.Generator | None = None,
                        correlation: float = 0.0, joint: bool = True,
                        hidden_as_albedo_area: bool = False) -> dict:
    """An estimate.json dict (schema v2) for a known scene: the twin experiments' estimate.

    ``std`` maps ``position``, ``normal``, ``area``, ``albedo`` (and ``specular``, ``exponent``
    for Phong patches) to a one-sigma std per number. The covariance is ``D R D`` with
    ``D = diag(std)`` and ``R`` equicorrelated at ``correlation`` within each kind (e.g. all
    albedos share a calibration error); with ``rng`` the reported values are one draw from
    N(truth, covariance) (normals renormalised), else the truth itself. With ``joint`` the dict
    carries the full ``covariance`` object, else only the per-number ``_std``. With
    ``hidden_as_albedo_area`` the hidden patches report only ``albedo_area`` (area and albedo
    null), as an estimate that cannot resolve their extent.
    """
    unknown = set(std) - set(_STD_KEYS)
    if unknown:
        raise EstimateInputError(f"std keys must be among {_STD_KEYS}; got {sorted(unknown)}.")
    hidden = scene.hidden
    names, truth, sig, kinds = [], [], [], []
    for k, p in enumerate(scene.patches):
        glossy = isinstance(p.brdf, Phong)
        proxy = hidden_as_albedo_area and hidden[k]
        items = [("position", p.centre), ("normal", p.normal)]
        items += ([("albedo_area", p.area * p.brdf.diffuse_albedo)] if proxy else
                  [("area", p.area), ("albedo", p.brdf.diffuse_albedo)])
        if glossy:
            items += [("specular", p.brdf.specular), ("exponent", p.brdf.exponent)]
        for kind, v in items:
            s = (std.get("albedo", 0.0) * p.area if kind == "albedo_area" else std.get(kind, 0.0))
            for a, x in enumerate(np.atleast_1d(v)):
                names.append(param_name(kind, k, a if np.ndim(v) else None))
                truth.append(float(x))
                sig.append(float(s))
                kinds.append(kind)
    truth, sig = np.array(truth), np.array(sig)
    R = np.eye(len(names))
    if correlation:
        same = np.array(kinds)[:, None] == np.array(kinds)[None, :]
        R = np.where(same, correlation, 0.0)
        np.fill_diagonal(R, 1.0)
    cov = sig[:, None] * R * sig[None, :]
    vals = truth.copy()
    if rng is not None:
        L = np.diag(sig) if not correlation else _psd_factor(cov)
        vals = truth + L @ rng.standard_normal(L.shape[1])
    got = dict(zip(names, vals))
    sd = dict(zip(names, sig))
    patches = []
    for k, p in enumerate(scene.patches):
        n = np.array([got[param_name("normal", k, a)] for a in range(3)])
        ent = {"id": k, "name": p.name or f"P{k}", "visible": bool(scene.visible[k]),
               "position": [got[param_name("position", k, a)] for a in range(3)],
               "position_std": [sd[param_name("position", k, a)] for a in range(3)],
               "normal": (n / np.linalg.norm(n)).tolist(),
               "normal_std": [sd[param_name("normal", k, a)] for a in range(3)],
               "unidentifiable": [], "notes": {}}
        for kind in ("area", "albedo", "albedo_area", "specular", "exponent"):
            nm = param_name(kind, k)
            if nm in got:
                ent[kind], ent[kind + "_std"] = float(got[nm]), float(sd[nm])
            elif kind in ("area", "albedo") and hidden_as_albedo_area and hidden[k]:
                ent[kind], ent[kind + "_std"] = None, None
                ent["unidentifiable"].append(kind)
                ent["notes"][kind] = "third bounces identify only albedo x area"
        patches.append(ent)
    return {"format": "stircasadi.estimate", "version": 2, "success": True, "verdict": "OK",
            "reasons": [], "frame": "capture", "source_xyz": scene.source.tolist(),
            "camera_xyz": scene.camera.tolist(), "patches": patches,
            "covariance": {"parameters": names, "matrix": cov.tolist()} if joint else None,
            "checks": [], "ambiguities": [], "priors": {}, "stages": {}}
