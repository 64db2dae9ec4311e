"""Study specs: the design (cells, seeds, sizes), the file formats, the cache key, and clear
refusals of bad specs."""
from __future__ import annotations

import math

import pytest

from stircasadi.errors import StudyError
from stircasadi.studies import Study, builtin_studies, cell_key, load_study

SPEC = {
    "name": "t", "repetitions": 3, "seed": 10,
    "base": {"problem": "three_patch", "noise": 1e-4},
    "factors": {"bin_scale": [1.0, 2.0], "solver": ["ipopt-exact", "lm-ad", "lm-fd"]},
    "sizes": {"small": {"repetitions": 1, "factors": {"solver": ["lm-ad"]}}},
}

TOML = """
name = "t"
repetitions = 3
seed = 10
[base]
problem = "three_patch"
noise = 1e-4
[factors]
bin_scale = [1.0, 2.0]
solver = ["ipopt-exact", "lm-ad", "lm-fd"]
[sizes.small]
repetitions = 1
factors.solver = ["lm-ad"]
"""

YAML = """
name: t
repetitions: 3
seed: 10
base: {problem: three_patch, noise: 1.0e-4}
factors:
  bin_scale: [1.0, 2.0]
  solver: [ipopt-exact, lm-ad, lm-fd]
sizes:
  small: {repetitions: 1, factors: {solver: [lm-ad]}}
"""


def test_cells_are_the_full_cross_times_repetitions_with_consecutive_seeds():
    st = Study.from_dict(SPEC)
    cells = st.cells()
    assert len(cells) == 2 * 3 * 3
    assert sorted({(c["bin_scale"], c["solver"]) for c in cells}) == sorted(
        (b, s) for b in (1.0, 2.0) for s in ("ipopt-exact", "lm-ad", "lm-fd"))
    for c in cells:
        assert c["seed"] == 10 + c["repetition"] and c["problem"] == "three_patch" and c["noise"] == 1e-4
    assert st.varied() == ["bin_scale", "solver"]


def test_cases_cross_the_factors_and_case_values_override_base():
    st = Study.from_dict({"name": "c", "base": {"problem": "three_patch", "noise": 1e-4},
                          "cases": [{"label": "a"}, {"label": "b", "noise": 1e-2}],
                          "factors": {"solver": ["lm-ad", "lm-fd"]}})
    cells = st.cells()
    assert len(cells) == 4
    assert {c["noise"] for c in cells if c["label"] == "b"} == {1e-2}
    assert {c["noise"] for c in cells if c["label"] == "a"} == {1e-4}


def test_a_case_narrows_the_design_for_itself():
    st = Study.from_dict({"name": "n", "repetitions": 3, "seed": 5,
                          "factors": {"bin_scale": [0.5, 1.0, 2.0], "solver": ["lm-ad", "lm-fd"]},
                          "cases": [{"problem": "three_patch"},
                                    {"problem": "hidden_corner", "repetitions": 1, "time_limit": 60.0,
                                     "factors": {"solver": ["ipopt-exact"]}}]})
    cells = st.cells()
    small = [c for c in cells if c["problem"] == "three_patch"]
    big = [c for c in cells if c["problem"] == "hidden_corner"]
    assert len(small) == 3 * 2 * 3 and len(big) == 3 * 1 * 1
    # the case's own list replaces the study's for that case only; the others still cross
    assert {c["solver"] for c in small} == {"lm-ad", "lm-fd"} and {c["solver"] for c in big} == {"ipopt-exact"}
    assert {c["bin_scale"] for c in big} == {0.5, 1.0, 2.0}
    assert {(c["repetition"], c["seed"]) for c in big} == {(0, 5)}
    # the design keys are not factors of the cell
    assert all("factors" not in c and "repetitions" not in c for c in cells)
    assert {c.get("time_limit") for c in big} == {60.0} and all("time_limit" not in c for c in small)
    for case, match in [({"problem": "three_patch", "repetitions": 0}, r"cases\[0\].repetitions"),
                        ({"problem": "three_patch", "factors": {"solver": "lm-ad"}}, "non-empty list"),
                        ({"problem": "three_patch", "factors": {"solver": ["newton"]}}, "got 'newton'"),
                        ({"problem": "three_patch", "factors": ["solver"]}, "table of factor lists")]:
        with pytest.raises(StudyError, match=match):
            Study.from_dict({"name": "bad", "cases": [case]})
    # the built-in accuracy-vs-time: every factor on the small problems, a few cells of the big
    avt = load_study("accuracy-vs-time").cells()
    per = {p: sum(c["problem"] == p for c in avt) for p in {c["problem"] for c in avt}}
    assert per == {"three_patch": 180, "hidden_corner": 180, "three_planes": 4, "three_planes_occluded": 2}
    assert load_study("accuracy-vs-time", "small").cells() == [c for c in avt if c["problem"] in
                                                                ("three_patch", "hidden_corner")]


def test_sizes_override_and_filter_cases():
    st = Study.from_dict(SPEC, size="small")
    assert len(st.cells()) == 2 and st.name == "t@small"
    hard = load_study("hard-cases", size="smoke")
    assert {c["label"] for c in hard.cells()} == {"albedo 0.999", "SNR 5 dB", "missing onset (one direct return)"}
    with pytest.raises(StudyError, match="no size 'huge'.*small"):
        Study.from_dict(SPEC, size="huge")


def test_toml_yaml_and_dict_give_the_same_cells(tmp_path):
    (tmp_path / "s.toml").write_text(TOML)
    (tmp_path / "s.yaml").write_text(YAML)
    a = Study.from_dict(SPEC).cells()
    assert load_study(tmp_path / "s.toml").cells() == a
    assert load_study(str(tmp_path / "s.yaml")).cells() == a
    assert load_study(tmp_path / "s.toml", size="small").cells() == Study.from_dict(SPEC, size="small").cells()


def test_builtin_studies_load_and_accuracy_vs_time_is_full_size():
    names = builtin_studies()
    assert {"accuracy-vs-time", "hard-cases", "effects", "accuracy-vs-noise"} <= set(names)
    assert len(load_study("accuracy-vs-time").cells()) >= 300
    for n in names:
        st = load_study(n)
        for size in st.sizes:
            assert 0 < len(load_study(n, size).cells()) <= len(st.cells())


@pytest.mark.parametrize("spec, match", [
    ({"name": "x", "base": {"problem": "three_patch", "nosie": 1e-3}}, "Unknown study factor 'nosie'.*Did you mean 'noise'"),
    ({"name": "x", "base": {"problem": "three_patch", "solver": "newton"}}, "solver.*ipopt-exact.*got 'newton'"),
    ({"name": "x", "base": {"problem": "three_patch"}, "factors": {"noise": 1e-3}}, "non-empty list"),
    ({"name": "x", "base": {"problem": "three_patch", "scene": "hard:coplanar"}}, "exactly one of 'problem'"),
    ({"name": "x", "base": {"noise": 1e-3}}, "neither"),
    ({"name": "x", "base": {"problem": "no_such_problem"}}, "Unknown problem 'no_such_problem'"),
    ({"name": "x", "base": {"scene": "hard:nope"}}, "Unknown hard case 'hard:nope'"),
    ({"name": "x", "base": {"problem": "three_patch", "noise": 1e-3, "snr_db": 3}}, "one of noise, snr_db"),
    ({"name": "x", "base": {"problem": "three_patch", "effect": "irf"}}, "effect and effect_state"),
    ({"name": "x", "repetitions": 0, "base": {"problem": "three_patch"}}, "repetitions must be"),
    ({"name": "x", "measures": ["speed"], "base": {"problem": "three_patch"}}, "Unknown measure"),
    ({"base": {"problem": "three_patch"}}, "needs a name"),
    ({"name": "x", "factor": {}}, "Unknown study key"),
])
def test_bad_specs_are_refused_with_the_fix(spec, match):
    with pytest.raises(StudyError, match=match):
        Study.from_dict(spec)


def test_bad_files_are_refused(tmp_path):
    (tmp_path / "bad.toml").write_text("name = ")
    with pytest.raises(StudyError, match="could not be parsed"):
        load_study(tmp_path / "bad.toml")
    with pytest.raises(StudyError, match="not found"):
        load_study(tmp_path / "missing.toml")
    with pytest.raises(StudyError, match="built-in studies are"):
        load_study("no-such-study")


def test_cell_key_depends_on_values_and_version_not_on_order(monkeypatch):
    a = {"problem": "three_patch", "noise": 1e-4, "seed": 1, "repetition": 0}
    b = dict(reversed(list(a.items())))
    assert cell_key(a) == cell_key(b)
    assert cell_key(a) != cell_key({**a, "seed": 2})
    assert cell_key({**a, "noise": math.nan}) == cell_key({**a, "noise": math.nan})
    import stircasadi

    k = cell_key(a)
    monkeypatch.setattr(stircasadi, "__version__", "9.9.9")
    assert cell_key(a) != k
