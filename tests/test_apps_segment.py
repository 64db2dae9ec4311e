"""apps.segment: three materials over 15 patches segmented from the estimate's BRDF and
covariance; the noise at which it starts to fail; ambiguous and unsegmented patches."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.apps.belief import SceneBelief
from stircasadi.apps.segment import SegmentSettings, segment, segment_features
from stircasadi.apps.twin import estimate_from_scene
from stircasadi.brdf import Lambertian, Phong
from stircasadi.errors import EstimateInputError
from stircasadi.problems._common import plane_patches
from stircasadi.scene import Patch, Scene

ALBEDOS = (0.3, 0.5, 0.7)          # three materials, 0.2 apart
PER_MATERIAL = 5


def _scene(brdfs=None):
    brdfs = brdfs or [Lambertian(a) for a in ALBEDOS]
    pts = plane_patches((0.0, 0.0, 1.5), (0, 0, -1), (1, 0, 0), 5, 3, 0.1, 0.004)
    order = np.random.default_rng(11).permutation(len(pts))          # materials interleaved
    mats = np.repeat(np.arange(len(brdfs)), PER_MATERIAL)[order]
    return Scene([Patch(p.centre, p.normal, p.area, brdfs[m], name=f"P{k}") for k, (p, m) in
                  enumerate(zip(pts, mats))]), mats


def _correct(seg, mats) -> bool:
    lab = seg.labels[np.argsort(seg.ids)]
    return seg.n_materials == 3 and all(len(set(lab[mats == m])) == 1 for m in range(3))


def _rate(sigma, seeds, scene, mats):
    ok = 0
    for s in range(seeds):
        d = estimate_from_scene(scene, {"position": 1e-3, "normal": 1e-3, "area": 1e-5, "albedo": sigma},
                                rng=np.random.default_rng(1000 + s))
        ok += _correct(segment(SceneBelief.from_estimate(d)), mats)
    return ok / seeds


def test_three_materials_are_segmented_at_the_stated_noise():
    """Albedo std 0.02 (the materials are 10 sigma apart): correct in >= 19 of 20 draws; the
    misses allowed are the test level's false splits (alpha = 0.01 per material)."""
    scene, mats = _scene()
    assert _rate(0.02, 20, scene, mats) >= 0.95
    d = estimate_from_scene(scene, {"albedo": 0.02, "area": 1e-5}, rng=np.random.default_rng(1))
    seg = segment(SceneBelief.from_estimate(d))
    assert _correct(seg, mats)
    for m in seg.materials:
        assert m["homogeneous"] and abs(m["mean"][0] - ALBEDOS[m["index"]]) < 4 * m["std"][0]
    assert seg.unsegmented == [] and seg.outliers == []


def test_noise_at_which_segmentation_starts_to_fail():
    """Sweep: success >= 90 % up to a noise, then falls. A patch is misassigned when its error
    exceeds half the 0.2 gap, so with 15 patches P(success) ~ (1 - 2 Phi(-0.1 / sigma))^15 drops
    below 0.9 near sigma = 0.04 (measured: benchmarks/apps.py segmentation table)."""
    scene, mats = _scene()
    sigmas = [0.02, 0.03, 0.04, 0.05, 0.07, 0.1]
    rates = [_rate(s, 15, scene, mats) for s in sigmas]
    assert rates[0] >= 0.9 and rates[-1] <= 0.2, rates
    onset = next(s for s, r in zip(sigmas, rates) if r < 0.9)
    assert 0.03 <= onset <= 0.07, (onset, rates)


def test_ambiguous_patch_between_two_materials_is_reported():
    x = np.array([0.3, 0.31, 0.29, 0.30, 0.70, 0.71, 0.69, 0.70, 0.5])[:, None]
    C = np.full((9, 1, 1), 0.01 ** 2)
    C[-1] = 0.15 ** 2                                  # the last patch is poorly measured
    r = segment_features(x, C)
    assert len(r["materials"]) == 2
    amb = {a["member"]: a for a in r["ambiguous"]}
    assert 8 in amb and len(amb[8]["candidates"]) == 1 and list(amb[8]["candidates"].values())[0] > 0.01
    assert set(amb) == {8}


def test_glossy_materials_use_every_phong_parameter():
    """Same albedo, different lobes: only specular/exponent tell them apart."""
    brdfs = [Phong(0.4, 0.1, 5.0), Phong(0.4, 0.4, 40.0), Lambertian(0.4)]
    scene, mats = _scene(brdfs)
    d = estimate_from_scene(scene, {"albedo": 0.01, "specular": 0.01, "exponent": 1.0, "area": 1e-5},
                            rng=np.random.default_rng(3))
    seg = segment(SceneBelief.from_estimate(d))
    assert _correct(seg, mats)
    kinds = sorted(m["kind"] for m in seg.materials)
    assert kinds == ["lambertian", "phong", "phong"]


def test_patches_without_albedo_or_std_are_reported_unsegmented():
    scene, _ = _scene()
    d = estimate_from_scene(scene, {"albedo": 0.02, "area": 1e-5}, rng=np.random.default_rng(0))
    d["patches"][3]["albedo_std"] = None
    d["covariance"] = None
    seg = segment(SceneBelief.from_estimate(d))
    assert [u["id"] for u in seg.unsegmented] == [3] and "no uncertainty" in seg.unsegmented[0]["reason"]
    assert 3 not in seg.ids.tolist()
    with pytest.raises(EstimateInputError, match="level"):
        segment(SceneBelief.from_estimate(d), SegmentSettings(level=0.7))
