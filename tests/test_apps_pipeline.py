"""Relighting from what the inverse route really returns (stircasadi.pipeline.estimate_capture on
the three-patch problem): an UNRELIABLE estimate is refused clearly; a reliable one re-renders the
capture it came from."""
from __future__ import annotations

import numpy as np
import pytest

from stircasadi.apps.belief import SceneBelief
from stircasadi.apps.relight import Illumination
from stircasadi.apps.render import RenderSettings, render
from stircasadi.errors import EstimateInputError
from stircasadi.irf import from_samples
from stircasadi.pipeline import estimate_capture
from stircasadi.problems import three_patch
from stircasadi.sensor import Sensor
from stircasadi.transport import simulate


@pytest.mark.slow
def test_relight_from_the_pipeline_estimate():
    scene, grid, sensor = three_patch.build_scene(), three_patch.build_grid(), three_patch.build_sensor()
    cap = sensor.capture(simulate(scene, grid, sensor=sensor), seed=0)
    cap.truth = None
    d0 = estimate_capture(cap).to_json_dict()
    # an uncalibrated three-patch scene: its normals and albedos are not identified (reported
    # null), and rendering refuses them by name
    if any(p.get("normal") is None or p.get("albedo") is None for p in d0["patches"]):
        with pytest.raises(EstimateInputError, match="is null"):
            SceneBelief.from_estimate(d0, allow_unreliable=True)
    # a calibrated camera (pixel rays, normals and footprints) identifies them
    sensor = Sensor(irf=sensor.irf, noise=sensor.noise, calibrated_camera=True)
    cap = sensor.capture(simulate(scene, grid, sensor=sensor), seed=0)
    cap.truth = None
    result = estimate_capture(cap)
    d = result.to_json_dict()
    if not result.success:
        with pytest.raises(EstimateInputError, match="UNRELIABLE"):
            SceneBelief.from_estimate(d)
        return
    # areas the estimate leaves null are declared: the problem's known patch size (an input)
    missing = {p["id"]: three_patch.AREA for p in d["patches"] if p.get("area") is None}
    if missing:
        with pytest.raises(EstimateInputError, match="area is null"):
            SceneBelief.from_estimate(d)
    b = SceneBelief.from_estimate(d, areas=missing)
    r = render(b, grid=cap.grid, sensor=Sensor(irf=from_samples(cap.irf, cap.grid.bin_width)),
               illumination=Illumination(np.ones(len(cap.ill_ids())), ids=cap.ill_ids()),
               settings=RenderSettings(bounces=2))
    np.testing.assert_array_equal(r.obs_ids, cap.obs_ids())
    measured = cap.stir.sum(axis=0)
    assert np.max(np.abs(r.relit - measured)) < 0.02 * measured.max()
    np.testing.assert_allclose(r.relit_steady, measured.sum(axis=1), rtol=0.02)
    assert r.metadata["std_complete"] == (not b.missing_std)
    assert np.all(np.isfinite(r.relit_std)) and np.all(r.relit_steady_std > 0)
