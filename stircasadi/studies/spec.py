"""A declarative study: factors crossed into cells, repetitions with seeds, measures to record.

When to use
-----------
Write a study as a TOML or YAML file (or build a ``Study`` in Python) and run it with
``stircasadi study SPEC --out DIR`` or ``run_study``. A spec reads::

    name = "my-study"
    description = "what it answers"
    repetitions = 3          # noise draws per design point, seeds seed, seed + 1, ...
    seed = 0
    measures = ["errors", "coverage", "iterations", "time", "memory", "flags"]
    sigma_limit = 4.0        # |err|/std beyond this is an error (hard cases, coverage tables)

    [base]                   # values every cell starts from
    problem = "three_patch"

    [factors]                # crossed in full (every combination), in this order
    noise = [1e-6, 1e-4]
    solver = ["ipopt-exact", "lm-ad"]

    [[cases]]                # optional explicit cells, each crossed with the factors
    label = "grazing"
    scene = "hard:grazing"

    [[cases]]                # a case may narrow the design for itself: its own factor
    problem = "three_planes" # lists (replacing the study's for this case only) and its
    repetitions = 1          # own number of repetitions (an expensive scene, fewer cells)
    factors.solver = ["ipopt-exact"]

    [[exclude]]              # optional: drop design points matching all these values
    label = "grazing"
    solver = "lm-ad"

    [sizes.smoke]            # a named size: overrides for a quick run (--size smoke)
    repetitions = 1
    factors.noise = [1e-4]

    [figures]                # the columns the pictures plot
    accuracy = ["err_position_m", "err_albedo"]
    time = "estimate_s"

Cells = cases x product(factors) x repetitions; a cell's parameters are ``base``, then the case,
then the factor values, then ``repetition`` and ``seed`` (= ``seed + repetition``). A case's own
``factors`` table replaces the study's lists of the factors it names (for that case only) and its
``repetitions`` the study's count. Every other key is checked against
``stircasadi.studies.factors.FACTORS``.
"""
from __future__ import annotations

import copy
import itertools
import json
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from ..errors import StudyError
from .factors import check_factor

__all__ = ["Study", "load_study", "builtin_studies", "MEASURES"]

MEASURES = ("errors", "coverage", "iterations", "time", "memory", "flags", "effects")
_TOP = {"name", "description", "repetitions", "seed", "measures", "sigma_limit", "base", "factors",
        "cases", "exclude", "sizes", "figures"}


@dataclass
class Study:
    """A study: what to vary, how often, and what to measure."""

    name: str
    """Short name (files, titles)."""
    description: str = ""
    """The question it answers."""
    base: dict = field(default_factory=dict)
    """Factor values every cell starts from."""
    factors: dict = field(default_factory=dict)
    """factor name -> list of values, crossed in full."""
    cases: list = field(default_factory=list)
    """Explicit cells (dicts of factor values), each crossed with ``factors``. A case may hold
    ``factors`` (a table of lists replacing the study's lists of those factors for this case) and
    ``repetitions`` (this case's count)."""
    exclude: list = field(default_factory=list)
    """Partial cells (dicts of factor values): a design point matching every value of one of
    them is dropped (e.g. a combination that does not finish)."""
    repetitions: int = 1
    """Noise draws per design point."""
    seed: int = 0
    """Seed of repetition 0; repetition r uses seed + r."""
    measures: tuple = MEASURES
    """Which measure groups the tables keep (``MEASURES``)."""
    sigma_limit: float = 4.0
    """The |err|/std limit of the 'no unflagged error beyond k sigma' measure."""
    sizes: dict = field(default_factory=dict)
    """name -> overrides (``repetitions``, ``seed``, ``base``, ``factors``, ``cases``, ``keep_cases``)."""
    figures: dict = field(default_factory=dict)
    """Columns the pictures plot (``accuracy``: list, ``time``: str)."""

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_dict(cls, d: dict, size: str | None = None) -> "Study":
        """A study from a parsed spec (a TOML/YAML document), at the named ``size``."""
        if not isinstance(d, dict):
            raise StudyError(f"A study spec is a table (mapping); got {type(d).__name__}.")
        unknown = set(d) - _TOP
        if unknown:
            raise StudyError(f"Unknown study key(s) {sorted(unknown)}; a spec has {sorted(_TOP)}. "
                             "Factor values go under [base], [factors] or [[cases]].")
        if "name" not in d:
            raise StudyError("A study spec needs a name (name = \"...\").")
        d = copy.deepcopy(d)
        sizes = d.pop("sizes", {}) or {}
        if size is not None:
            if size not in sizes:
                raise StudyError(f"Study {d['name']!r} has no size {size!r}; sizes: "
                                 f"{', '.join(sizes) or '(none: run it without --size)'}.")
            d = _apply_size(d, sizes[size])
            d["name"] = f"{d['name']}" + (f"@{size}" if size else "")
        study = cls(name=str(d["name"]), description=str(d.get("description", "")),
                    base=dict(d.get("base") or {}), factors=dict(d.get("factors") or {}),
                    cases=list(d.get("cases") or []), exclude=list(d.get("exclude") or []),
                    repetitions=d.get("repetitions", 1),
                    seed=d.get("seed", 0), measures=tuple(d.get("measures", MEASURES)),
                    sigma_limit=d.get("sigma_limit", 4.0), sizes=sizes,
                    figures=dict(d.get("figures") or {}))
        return study.validate()

    @classmethod
    def from_file(cls, path, size: str | None = None) -> "Study":
        """Read a TOML (``.toml``) or YAML (``.yaml``/``.yml``) spec."""
        path = Path(path)
        if not path.is_file():
            raise StudyError(f"Study spec not found: {path}. Give a .toml or .yaml file or one of the "
                             f"built-in studies: {', '.join(builtin_studies())}.")
        text = path.read_text()
        try:
            if path.suffix == ".toml":
                import tomllib

                d = tomllib.loads(text)
            elif path.suffix in (".yaml", ".yml"):
                import yaml

                d = yaml.safe_load(text)
            else:
                raise StudyError(f"Study spec {path} must end in .toml, .yaml or .yml; got "
                                 f"{path.suffix or 'no suffix'!r}.")
        except StudyError:
            raise
        except Exception as exc:  # tomllib.TOMLDecodeError, yaml.YAMLError
            raise StudyError(f"Study spec {path} could not be parsed: {exc}") from exc
        return cls.from_dict(d, size=size)

    def validate(self) -> "Study":
        """Check the design; raise ``StudyError`` naming what is wrong and the fix."""
        _check_repetitions("repetitions", self.repetitions)
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise StudyError(f"seed must be an integer >= 0; got {self.seed!r}.")
        bad = [m for m in self.measures if m not in MEASURES]
        if bad:
            raise StudyError(f"Unknown measure(s) {bad}; measures are {', '.join(MEASURES)}.")
        if not (isinstance(self.sigma_limit, (int, float)) and self.sigma_limit > 0):
            raise StudyError(f"sigma_limit must be a number > 0; got {self.sigma_limit!r}.")
        _check_factor_lists("[factors]", self.factors, "under [base]")
        for where, d in ([("base", self.base)] + [(f"cases[{i}]", c) for i, c in enumerate(self.cases)]
                         + [(f"exclude[{i}]", c) for i, c in enumerate(self.exclude)]):
            if not isinstance(d, dict):
                raise StudyError(f"{where} must be a table of factor values; got {type(d).__name__}.")
            for k, v in d.items():
                if where.startswith("cases[") and k in _CASE_KEYS:
                    _check_case_key(where, k, v)
                    continue
                check_factor(k, v)
        cells = self.cells()
        if not cells:
            raise StudyError(f"Study {self.name!r} has no cells.")
        for c in cells:
            _check_cell(c)
        _check_sources({c.get("problem") for c in cells} - {None}, {c.get("scene") for c in cells} - {None})
        return self

    # ------------------------------------------------------------------ design
    def _design(self) -> list[tuple[dict, int]]:
        """(design point, repetitions) for every case x factor combination not excluded."""
        out = []
        for case in (self.cases or [{}]):
            factors = {**self.factors, **(case.get("factors") or {})}
            reps = case.get("repetitions", self.repetitions)
            fixed = {k: v for k, v in case.items() if k not in _CASE_KEYS}
            names = list(factors)
            combos = list(itertools.product(*(factors[n] for n in names))) if names else [()]
            for combo in combos:
                p = {**self.base, **fixed, **dict(zip(names, combo))}
                if not any(all(k in p and p[k] == v for k, v in ex.items()) for ex in self.exclude):
                    out.append((p, reps))
        return out

    def design_points(self) -> list[dict]:
        """Cells without repetition: base + case + factor combination."""
        return [p for p, _ in self._design()]

    def cells(self) -> list[dict]:
        """Every cell: a design point with ``repetition`` and ``seed``."""
        return [{**p, "repetition": r, "seed": self.seed + r}
                for p, reps in self._design() for r in range(reps)]

    def varied(self) -> list[str]:
        """Factor names that take more than one value across the cells."""
        pts = self.design_points()
        keys = sorted({k for p in pts for k in p})
        return [k for k in keys if len({json.dumps(p.get(k), sort_keys=True) for p in pts}) > 1]

    def to_dict(self) -> dict:
        return {"name": self.name, "description": self.description, "repetitions": self.repetitions,
                "seed": self.seed, "measures": list(self.measures), "sigma_limit": self.sigma_limit,
                "base": self.base, "factors": self.factors, "cases": self.cases, "exclude": self.exclude,
                "figures": self.figures}


def _apply_size(d: dict, over: dict) -> dict:
    allowed = {"repetitions", "seed", "base", "factors", "cases", "keep_cases", "description", "exclude"}
    unknown = set(over) - allowed
    if unknown:
        raise StudyError(f"Unknown key(s) {sorted(unknown)} in a size; allowed: {sorted(allowed)}.")
    for k in ("repetitions", "seed", "description", "cases", "exclude"):
        if k in over:
            d[k] = over[k]
    for k in ("base", "factors"):
        if k in over:
            d[k] = {**(d.get(k) or {}), **over[k]}
    if "keep_cases" in over:
        keep = set(over["keep_cases"])
        d["cases"] = [c for c in d.get("cases", []) if c.get("label") in keep]
    return d


#: keys a case may hold besides factor values: its own factor lists and repetitions
_CASE_KEYS = ("factors", "repetitions")


def _check_repetitions(where: str, value) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise StudyError(f"{where} must be an integer >= 1; got {value!r}.")


def _check_factor_lists(where: str, factors: dict, single: str) -> None:
    """Every factor under ``where`` is a non-empty list of allowed values (``single``: where a
    single value goes instead)."""
    for k, v in factors.items():
        if not isinstance(v, list) or not v:
            raise StudyError(f"Factor {k!r} under {where} must be a non-empty list of values; "
                             f"got {v!r}. A single value goes {single}.")
        for x in v:
            check_factor(k, x)


def _check_case_key(where: str, key: str, value) -> None:
    if key == "repetitions":
        _check_repetitions(f"{where}.repetitions", value)
    elif not isinstance(value, dict):
        raise StudyError(f"{where}.factors must be a table of factor lists (factors.solver = "
                         f"[\"ipopt-exact\"]); got {type(value).__name__}.")
    else:
        _check_factor_lists(f"{where}.factors", value, "in the case itself")


def _check_cell(c: dict) -> None:
    has_problem, has_scene = "problem" in c, "scene" in c
    if has_problem == has_scene:
        raise StudyError("Each cell needs exactly one of 'problem' (a problem script) or 'scene' (a "
                         f"generator); got {'both' if has_problem else 'neither'} in {_short(c)}.")
    grid_keys = [k for k in ("bin_width", "bin_scale") if k in c]
    if len(grid_keys) > 1:
        raise StudyError(f"Give one of bin_width or bin_scale, not both; got both in {_short(c)}.")
    noise_keys = [k for k in ("noise", "snr_db", "photons") if k in c]
    if len(noise_keys) > 1:
        raise StudyError(f"Give one of noise, snr_db or photons per cell; got {noise_keys} in {_short(c)}.")
    model = c.get("noise_model")
    if model == "poisson" and "photons" not in c:
        raise StudyError(f"noise_model='poisson' needs photons (counts in the brightest bin); {_short(c)}.")
    if model in ("none", "sensor") and noise_keys:
        raise StudyError(f"noise_model={model!r} cannot be combined with {noise_keys[0]}; {_short(c)}.")
    if ("effect" in c) != ("effect_state" in c):
        raise StudyError(f"effect and effect_state go together; {_short(c)}.")


def _check_sources(problems: set, scenes: set) -> None:
    """Unknown problems and hard cases are refused before any cell runs."""
    from ..errors import StircasadiError
    from ..problem import load_problem
    from .hardcases import HARD_CASES

    for p in sorted(problems):
        try:
            load_problem(p)
        except StircasadiError as exc:
            raise StudyError(f"problem {p!r}: {exc}") from exc
    from .cell import _import_callable

    for s in sorted(scenes):
        if s.startswith("hard:"):
            if s[5:] not in HARD_CASES:
                raise StudyError(f"Unknown hard case {s!r}; the cases are "
                                 f"{', '.join('hard:' + k for k in HARD_CASES)}.")
        else:
            _import_callable(s)


def _short(c: dict) -> str:
    return json.dumps({k: v for k, v in c.items() if k not in ("repetition",)}, sort_keys=True)[:200]


def builtin_studies() -> list[str]:
    """Names of the studies shipped with the package (``stircasadi/studies/specs/*.toml``)."""
    folder = resources.files("stircasadi.studies") / "specs"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_study(spec, size: str | None = None) -> Study:
    """A ``Study`` from a ``Study``, a dict, a spec file path or a built-in study name."""
    if isinstance(spec, Study):
        if size is None:
            return spec.validate()
        return Study.from_dict({**spec.to_dict(), "sizes": spec.sizes}, size=size)
    if isinstance(spec, dict):
        return Study.from_dict(spec, size=size)
    path = Path(spec)
    if path.suffix in (".toml", ".yaml", ".yml") or path.exists():
        return Study.from_file(path, size=size)
    if str(spec) in builtin_studies():
        res = resources.files("stircasadi.studies") / "specs" / f"{spec}.toml"
        import tomllib

        return Study.from_dict(tomllib.loads(res.read_text()), size=size)
    raise StudyError(f"Unknown study {spec!r}: not a file, and the built-in studies are "
                     f"{', '.join(builtin_studies())}.")
