"""``estimate --method surface`` on a full STIR (``stircasadi.nlos.stir_estimate``): the joint
fit's visible patches handed to the surface route, in the joint fit's own frame, and the
estimate.json it writes."""
from types import SimpleNamespace

import numpy as np
import pytest

from stircasadi.nlos.stir_estimate import SUPERSEDED, add_stir_surface
from stircasadi.nlos.stir_surface import VisiblePatches, hidden_surface_from_stir
from stircasadi.nlos.surface import SurfaceSettings
from stircasadi.problems import three_planes_occluded as P
from stircasadi.problems._common import paper_sensor
from stircasadi.scene import Scene
from stircasadi.transport import simulate


@pytest.fixture(scope="module")
def small_fig13():
    """Every other patch of Fig. 13's three planes (4 x 4 each): 32 visible, 16 hidden behind
    the screen; 1e-8 relative noise."""
    base = P.build_scene()
    idx = [s * 49 + 7 * r + c for s in range(3) for r in range(0, 7, 2) for c in range(0, 7, 2)]
    sc = Scene([base.patches[k] for k in idx], occluders=base.occluders)
    sen = paper_sensor(1e-8)
    return sc, sen.capture(simulate(sc, P.build_grid(), sensor=sen), seed=2)


def _joint_result(vis: VisiblePatches, source, camera, checks):
    """What ``add_stir_surface`` reads of a joint ``EstimateResult``: the fitted values and the
    view (ids, source, camera), and the joint estimate.json's lists."""
    est = SimpleNamespace(values={"position": vis.positions, "normal": vis.normals, "albedo": vis.albedos,
                                  "area": vis.areas}, success=True)
    patches = [{"id": int(i), "visible": True, "position": vis.positions[k].tolist()} for k, i in enumerate(vis.ids)]
    js = {"success": all(c["passed"] for c in checks), "verdict": "?", "reasons": [], "checks": checks,
          "patches": patches, "stages": {"joint": {}}, "priors": {}}
    return SimpleNamespace(json=js, fit=SimpleNamespace(estimate=est),
                           view=SimpleNamespace(ids=np.asarray(vis.ids), source=np.asarray(source, float),
                                                camera=np.asarray(camera, float)), extra={})


def test_stir_surface_route_in_the_joint_fits_frame(small_fig13, monkeypatch):
    """The joint fit places the scene in its own frame (source at its origin). Handing the route
    the visible patches, source and camera all translated by t must give the library route's
    surface translated by t (same depth map to 1 um: the subtraction leaves 1e-13 differences in
    the traces; points X + t), not a surface built with the capture's own source and camera (a
    rotation would not do as the known answer: the frame search's box is world-aligned, so its
    grid turns with the axes); the estimate.json
    appends every node as a hidden patch after the visible ones and marks a failed joint chi2
    check as superseded by the surface's chi2."""
    sc, cap = small_fig13
    vid = np.flatnonzero(~sc.hidden)
    vis = VisiblePatches(vid, sc.positions[vid], sc.normals[vid], sc.albedos[vid], sc.areas[vid], None)
    st = SurfaceSettings(n_nodes=4, levels=1, known_gain=True, max_iter=3, fit_sigma=False)
    step = int(np.ceil(32 * 32 / 300))
    # a stated frame, no refinement: on 16 hidden patches the frame search's plane through its
    # few brightest voxels is ill-conditioned (1e-13 changes of the traces turn it), which is
    # not what this test is about
    u, v = np.array([0.0, 1.0, 0.0]), np.array([-0.6, 0.0, -0.8])
    fr = (np.array([-0.6, 0.0, 0.9]), u, v, np.cross(u, v))
    ref = hidden_surface_from_stir(cap, vis, st, ill_step=step, frame=fr, refine=False)
    t = np.array([0.4, -1.2, 0.7])
    moved = VisiblePatches(vid, sc.positions[vid] + t, sc.normals[vid], sc.albedos[vid],
                           sc.areas[vid], None)
    checks = [{"name": "solver", "passed": True, "value": 1, "limit": 1, "message": "ok"},
              {"name": "chi2", "passed": False, "value": 9.0, "limit": 1.2, "message": "chi2/dof 9"}]
    res = _joint_result(moved, cap.source_xyz + t, cap.camera_xyz + t, checks)
    import stircasadi.nlos.stir_estimate as E

    frt = (fr[0] + t,) + fr[1:]
    monkeypatch.setattr(E, "hidden_surface_from_stir", lambda c, v, s, ill_step: hidden_surface_from_stir(
        c, v, s, ill_step=ill_step, frame=frt, refine=False))
    out = add_stir_surface(res, cap, max_traces=300, settings=st)
    got = out.extra["stir_surface"].surface
    np.testing.assert_allclose(got.depth, ref.surface.depth, atol=1e-6)
    assert np.ptp(ref.surface.depth) > 0      # the fit moved the nodes
    np.testing.assert_allclose(got.points(), ref.surface.points() + t, atol=1e-6)
    d = out.json
    hid = [p for p in d["patches"] if not p["visible"]]
    assert len(d["patches"]) == 32 + 16 and len(hid) == 16
    assert min(p["id"] for p in hid) == vid.max() + 1                 # ids after the visible ones
    assert sum(p["in_mask"] for p in hid) == int(got.mask.sum())
    c2 = {c["name"]: c for c in d["checks"]}
    assert c2["chi2"]["superseded_by"] == "surface-chi2" and "surface-chi2" in c2
    assert not any(r.startswith("chi2:") for r in d["reasons"])
    surf = [c for c in c2 if c.startswith("surface-")]
    assert set(surf) == {"surface-solver", "surface-chi2", "surface-detection", "surface-explained-returns"}
    assert d["success"] == (all(c2[c]["passed"] for c in surf) and got.success)
    assert "chi2" in SUPERSEDED and d["stages"]["surface"]["ill_step"] == step


def test_surface_route_is_skipped_and_flagged_when_the_time_is_spent(small_fig13):
    sc, cap = small_fig13
    vid = np.flatnonzero(~sc.hidden)
    vis = VisiblePatches(vid, sc.positions[vid], sc.normals[vid], sc.albedos[vid], sc.areas[vid], None)
    res = _joint_result(vis, cap.source_xyz, cap.camera_xyz, [])
    out = add_stir_surface(res, cap, time_left=0.0)
    assert out.json["success"] is False and out.json["verdict"] == "UNRELIABLE"
    assert "time limit" in out.json["reasons"][-1] and "stir_surface" not in out.extra


def test_stir_surface_refuses_a_hidden_count_and_relay_methods(small_fig13):
    from stircasadi.errors import ModelError
    from stircasadi.pipeline import estimate_capture

    sc, cap = small_fig13
    with pytest.raises(ModelError, match="one surface"):
        estimate_capture(cap, hidden=3, method="surface")
    with pytest.raises(ModelError, match="method='surface'"):
        estimate_capture(cap, method="lct")
