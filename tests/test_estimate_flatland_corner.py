"""Twin experiment on the flatland hidden corner (every patch, the source and the camera in y = 0).

The geometry estimate is built as the geometry stage gives it: a rotated source-origin frame,
hidden ids re-assigned in another order, hidden normals NaN. Hidden patches are matched to the
truth by position after a Kabsch alignment about the source, never by id.

Why visible normals are given here: with two visible patches and a co-located source and camera,
the first bounce does not depend on any normal and the 2nd/3rd bounces see, per hidden patch h,
only sqrt(rho_h) c_h0 c_0h and sqrt(rho_h) c_h1 c_1h, plus c_01 c_10 once: 5 numbers for 6
unknowns (two visible in-plane angles, rho_h and one angle per hidden patch). So either the
visible normals are known (tested: everything identifiable), or they are not and the Fisher
analysis must say so (tested: one null direction, hidden albedos/normals flagged, nothing
reported as a result).

Tolerances: k = 4 sigma on every parameter with seeded noise (a 3-sigma target; 4 leaves room
for 12 parameters x 2 noise levels without hiding a bias: the bias of assumed normals was
100-1000 sigma); noise-free: round-off (IPOPT stops at acceptable tolerance, 1e-8 relative).
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from stircasadi.problems import hidden_corner
from stircasadi.brdf import Lambertian
from stircasadi.estimate import estimate_reflectance, report_table
from stircasadi.estimate.pipeline import _frame_alignment, match_hidden_to_truth
from stircasadi.geometry import GeometryEstimate
from stircasadi.scene import Patch, Scene
from stircasadi.sensor import GaussianNoise, Sensor
from stircasadi.timegrid import TimeGrid
from stircasadi.transport import simulate

K_SIGMA = 4.0
ORDER = [0, 1, 3, 2]          # hidden ids re-assigned in another order
TH = 0.7                      # frame rotation about y (the plane stays y = 0)
ROT = np.array([[np.cos(TH), 0, np.sin(TH)], [0, 1, 0], [-np.sin(TH), 0, np.cos(TH)]])


def _unit(v):
    v = np.asarray(v, float)
    return tuple(v / np.linalg.norm(v))


def flatland_corner() -> Scene:
    return Scene([Patch((-0.20, 0.0, 1.20), (0.0, 0.0, -1.0), 0.01, Lambertian(0.8), name="V1"),
                  Patch((0.45, 0.0, 0.90), _unit((-1.0, 0.0, -0.3)), 0.01, Lambertian(0.6), name="V2"),
                  Patch((-0.45, 0.0, 0.60), _unit((0.3, 0.0, 1.0)), 0.04, Lambertian(0.7), name="H1"),
                  Patch((0.10, 0.0, 0.55), _unit((-0.2, 0.0, 1.0)), 0.04, Lambertian(0.5), name="H2")],
                 name="flatland_corner")


def _capture(rel, seed=11):
    sc = flatland_corner()
    irf = hidden_corner.build_sensor().irf
    se = Sensor(irf=irf, noise=GaussianNoise(relative=rel)) if rel > 0 else Sensor(irf=irf)
    tr = simulate(sc, TimeGrid(0.0, 0.005, 1024), se)
    return sc, se.capture(tr, seed=seed, noise=rel > 0)


def _geometry(sc, visible_normals=True, extra_hidden=None):
    pos = sc.positions[ORDER] @ ROT.T
    vis = ~sc.hidden[ORDER]
    nor = np.full((len(pos), 3), np.nan)
    if visible_normals:
        nor[vis] = (sc.normals[ORDER] @ ROT.T)[vis]
    if extra_hidden is not None:
        pos = np.vstack([pos, extra_hidden])
        vis = np.append(vis, False)
        nor = np.vstack([nor, np.full(3, np.nan)])
    return GeometryEstimate(ids=np.arange(len(pos)), positions=pos, visible=vis, normals=nor,
                            source_xyz=np.zeros(3), camera_xyz=np.zeros(3))


def _errors(e, sc):
    """Per estimated patch: truth index, albedo error, position error (estimate frame), normal angle."""
    pos = np.asarray(e.values["position"], float)
    vis = e.visible
    P = np.vstack([pos[vis], np.zeros((1, 3))])
    Q = np.vstack([sc.positions[e.ids[vis]], np.zeros((1, 3))])
    A = _frame_alignment(P, Q, e.extra.get("frame"))  # estimate frame -> truth frame: pos @ A
    t = match_hidden_to_truth(pos @ A, vis, e.ids, sc.positions, ~sc.hidden)
    ok = t >= 0
    alb = np.where(ok, e.values["albedo"] - sc.albedos[np.maximum(t, 0)], np.nan)
    dpos = np.where(ok[:, None], pos - sc.positions[np.maximum(t, 0)] @ A.T, np.nan)
    ang = np.degrees(np.arccos(np.clip(np.sum((e.values["normal"] @ A) * sc.normals[np.maximum(t, 0)], 1), -1, 1)))
    return t, alb, dpos, ang


@pytest.mark.parametrize("rel", [1e-7, 1e-6])
def test_albedos_positions_and_hidden_normals_within_k_sigma(rel):
    sc, cap = _capture(rel)
    e = estimate_reflectance(cap, _geometry(sc))
    assert e.success and e.extra["fisher_null_dim"] == 0
    t, alb, dpos, ang = _errors(e, sc)
    assert sorted(t.tolist()) == [0, 1, 2, 3]
    h = np.flatnonzero(~e.visible)
    assert np.all(e.free["normal"][h]) and not np.any(e.free["normal"][e.visible])
    for k in range(4):
        assert np.all(np.isfinite(e.values["albedo"])) and np.isfinite(e.std["albedo"][k])
        assert abs(alb[k]) <= K_SIGMA * e.std["albedo"][k], (k, alb[k], e.std["albedo"][k])
    for k in h:
        sp = e.std["position"][k]
        assert np.all(np.isfinite(sp)) and np.all(np.abs(dpos[k]) <= K_SIGMA * sp + 1e-9), (k, dpos[k], sp)
        sn_deg = np.degrees(np.linalg.norm(e.std["normal"][k]))
        assert np.isfinite(sn_deg) and ang[k] <= K_SIGMA * sn_deg, (k, ang[k], sn_deg)
        # and the result is a useful one at this noise: normals within a degree, albedo 1 %
        assert ang[k] < 1.0 and abs(alb[k]) < 0.01
    js = e.to_json_dict()
    json.dumps(js)
    p = js["patches"][h[0]]
    assert p["normal_source"].startswith("estimated") and len(p["normal_std"]) == 3
    assert abs(np.linalg.norm(p["normal"]) - 1.0) < 1e-12
    tab = report_table(e, cap.truth)
    assert "normal" in tab and "deg" in tab


def test_noise_free_recovers_the_truth_to_round_off():
    sc, cap = _capture(0.0)
    e = estimate_reflectance(cap, _geometry(sc))
    t, alb, dpos, ang = _errors(e, sc)
    assert np.max(np.abs(alb)) < 1e-8
    assert np.nanmax(np.abs(dpos)) < 1e-9
    assert np.max(ang[~e.visible]) < 1e-5


def test_unknown_visible_normals_leave_a_flagged_null_direction():
    sc, cap = _capture(1e-7)
    e = estimate_reflectance(cap, _geometry(sc, visible_normals=False))
    assert e.success and e.extra["fisher_null_dim"] == 1
    t, alb, dpos, _ = _errors(e, sc)
    v = np.flatnonzero(e.visible)
    assert np.all(np.abs(alb[v]) <= K_SIGMA * e.std["albedo"][v])  # first bounce: unaffected
    h = np.flatnonzero(~e.visible)
    assert np.all(np.isfinite(e.values["albedo"])) and np.all(np.isfinite(e.values["normal"]))
    assert np.nanmax(np.abs(dpos[h])) < 1e-3  # distances come from delays
    assert not np.any(e.identifiable["albedo"][h]) and not np.any(e.identifiable["normal"][h])
    js = e.to_json_dict()
    assert all(js["patches"][k]["albedo"] is None and "normal" in js["patches"][k]["unidentifiable"]
               for k in h)


def test_hidden_patch_on_the_anchor_line_is_flagged_not_fatal():
    sc, cap = _capture(1e-7)
    z = sc.positions[ORDER] @ ROT.T
    g = _geometry(sc, extra_hidden=0.5 * (z[0] + z[1]))  # spurious patch between the anchors
    e = estimate_reflectance(cap, g)
    assert e.success
    k = 4
    assert 4 in e.extra["degenerate_hidden"] and not e.identifiable["position"][k]
    assert any("ambiguous" in f for f in e.flags)
    js = e.to_json_dict()
    assert "ambiguous" in js["patches"][k] and "position" in js["patches"][k]["unidentifiable"]
    t, alb, dpos, ang = _errors(e, sc)
    assert t[k] == -1  # matched to no true patch
    good = [i for i in range(4)]
    assert np.all(np.abs(alb[good]) <= K_SIGMA * e.std["albedo"][good])
    assert "no truth" in report_table(e, cap.truth)
