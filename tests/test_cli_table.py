"""The printed table (``stircasadi.report.table``): one row per patch with the final numbers, units
in the header, the scene's names, σ and err/σ worked out by hand, a compact form for large scenes."""
from __future__ import annotations

import numpy as np

from stircasadi.report import table


def _truth(n):
    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), np.full(n, 1.0)])
    return {"positions": P, "normals": np.tile([0.0, 0.0, -1.0], (n, 1)), "areas": np.full(n, 0.01),
            "albedo": np.full(n, 0.5), "visible": np.ones(n, bool)}


def _patch(i, pos, pos_std, albedo=0.5, albedo_std=0.01, **kw):
    p = {"id": i, "name": f"V{i}", "visible": True, "position": list(pos), "position_std": list(pos_std),
         "normal": [0.0, 0.0, -1.0], "normal_std": [0.01, 0.0, 0.0], "albedo": albedo,
         "albedo_std": albedo_std, "area": 0.01, "area_std": 1e-4, "notes": {}}
    p.update(kw)
    return p


def _rows(text):
    return [ln for ln in text.splitlines() if ln[:1].isdigit()]


def test_err_over_sigma_worked_by_hand_and_units_in_the_header():
    t = _truth(2)
    # patch 0: 1 mm off along x with sigma 0.5 mm per component -> err 1 mm, err/sigma 2.00
    # its albedo 0.53 +- 0.02 against 0.5 -> err/sigma 1.50
    p0 = _patch(0, t["positions"][0] + [1e-3, 0, 0], [5e-4, 5e-4, 5e-4], albedo=0.53, albedo_std=0.02)
    p1 = _patch(1, t["positions"][1], [5e-4] * 3)
    est = {"frame": "capture", "source_xyz": [0, 0, 0], "patches": [p0, p1]}
    text = table(est, t, names=["left", "right"])
    head = text.splitlines()[:2]
    for unit in ("position (m)", "σ mm", "pos err mm", "err/σ", "σ °", "area (cm²)", "albedo"):
        assert unit in "\n".join(head)
    r0, r1 = _rows(text)
    cells = r0.split()
    assert cells[:3] == ["0", "left", "yes"]
    assert cells[3:6] == [f"{v:.4f}" for v in t["positions"][0] + [1e-3, 0, 0]]
    assert cells[6] == "0.87" and cells[7] == "1" and cells[8] == "2.00"   # |σ| = 0.5 mm sqrt 3
    assert "0.5300" in cells and cells[cells.index("0.5300") + 1:cells.index("0.5300") + 3] == ["0.02", "1.50"]
    assert r1.split()[1] == "right" and r1.split()[8] == "0.00"


def test_null_numbers_given_numbers_and_hidden_patches():
    t = _truth(3)
    t["visible"][2] = False
    p0 = _patch(0, t["positions"][0], [1e-4] * 3, normal_std=[0.0, 0.0, 0.0], notes={"normal": "given"})
    p1 = _patch(1, t["positions"][1], [1e-4] * 3, albedo=None, albedo_std=None,
                unidentifiable=["albedo"], notes={"albedo": "third bounces identify albedo x area only"})
    h = _patch(9, t["positions"][2] + [0, 0, 2e-3], [1e-3] * 3, visible=False, area=None, area_std=None,
               albedo_area=0.004, albedo_area_std=1e-4, name="H9")
    est = {"frame": "capture", "source_xyz": [0, 0, 0], "patches": [p0, p1, h]}
    text = table(est, t, names=["a", "b", "c"])
    r0, r1, r2 = _rows(text)
    assert "given" in r0                                # an input, not an estimate
    assert "n/i" in r1.split()                           # not identifiable
    assert r2.split()[:3] == ["9", "c", "no"]            # hidden patch matched to the true 'c'
    assert "albedo·area (cm²)" in text and "40" in r2.split()   # 0.004 m^2 = 40 cm^2
    assert "n/i: not identifiable" in text


def test_compact_form_for_a_large_scene():
    n = 147
    t = _truth(n)
    # errors of exactly 0.5 sigma on half the patches and 3 sigma on the other half
    pats = [_patch(i, t["positions"][i] + [(0.5 if i % 2 else 3.0) * 1e-3, 0, 0], [1e-3] * 3)
            for i in range(n)]
    est = {"frame": "capture", "source_xyz": [0, 0, 0], "patches": pats}
    text = table(est, t)
    rows = _rows(text)
    assert len(rows) == 20 and all(int(r.split()[0]) % 2 == 0 for r in rows)   # the worst first
    assert "127 more patches in estimate.json" in text
    line = next(ln for ln in text.splitlines() if ln.startswith("position:"))
    assert f"{n} estimated" in line and "<= 1 for 50%" in line and "max 3.00" in line
    assert len(text.splitlines()) < 40
    blind = table(est)            # without a truth: hidden patches first, then the largest σ
    assert "err/σ" not in blind and "position (σ mm): reported for 147 of 147 patches" in blind


def test_geometry_only_estimate_and_empty_estimate():
    t = _truth(3)
    est = {"frame": "capture", "patches": [{"id": i, "visible": True, "position": list(t["positions"][i])}
                                           for i in range(3)]}
    text = table(est, t)
    assert len(_rows(text)) == 3 and "albedo" not in text.splitlines()[0]
    assert table({"patches": []}) == "(no patches in the estimate)"
