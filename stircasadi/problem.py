"""Find, load and run problem scripts: a name in ``stircasadi.problems`` or a path to a ``.py`` file.

A problem script is an importable factory module (STYLE.md rule 9). It defines
``build_scene()``, ``build_grid()`` and ``build_sensor()``, and may define ``NAME``,
``DESCRIPTION`` (the line ``stircasadi problems`` prints; default: the docstring's first sentence),
``truth()`` (default: the scene's ``truth_dict()``) and ``ESTIMATE`` (options of
``stircasadi run``: ``{"stage": "reflectance"}`` for a reflectance twin with known geometry,
``"brdf"``, ``"hidden"``, ``"time_limit"`` in seconds).
Problem scripts use absolute imports only, so a copy placed anywhere runs by path::

    stircasadi run my_scene.py        python my_scene.py
"""
from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

from .errors import StircasadiError

DEFAULT_PROBLEM = "hidden_corner"
REQUIRED = ("build_scene", "build_grid", "build_sensor")


def _folder() -> Path:
    from . import problems

    return Path(problems.__file__).parent


def list_problems() -> list[str]:
    """Names of the problem scripts shipped in ``stircasadi.problems``."""
    return sorted(p.stem for p in _folder().glob("*.py") if not p.stem.startswith("_"))


def describe(mod: ModuleType) -> str:
    """The one-line description of a problem: its ``DESCRIPTION``, else its docstring's first
    sentence."""
    if isinstance(getattr(mod, "DESCRIPTION", None), str):
        return mod.DESCRIPTION
    doc = (mod.__doc__ or "").strip().split("\n\n")[0].replace("\n", " ")
    first = doc.split(". ")[0].rstrip(".")
    return first + "." if first else "(no description)"


def load_problem(name_or_path: str | None = None) -> ModuleType:
    """Import a problem by name (``stircasadi.problems.<name>``) or from a file path."""
    name_or_path = name_or_path or DEFAULT_PROBLEM
    path = Path(name_or_path)
    if path.suffix == ".py" or path.exists():
        if not path.is_file():
            raise StircasadiError(f"Problem script not found: {path} (give a .py file or one of the "
                                  f"names {', '.join(list_problems())}).")
        spec = importlib.util.spec_from_file_location(f"_problem_{path.stem}", path)
        mod = importlib.util.module_from_spec(spec)
        try:
            spec.loader.exec_module(mod)
        except Exception as exc:
            raise StircasadiError(f"Problem script {path} failed to import: {type(exc).__name__}: "
                                  f"{exc}. A problem script uses absolute imports "
                                  "(from stircasadi.problems._common import ...).") from exc
    else:
        key = name_or_path.replace("-", "_")
        if key not in list_problems():
            raise StircasadiError(f"Unknown problem {name_or_path!r}; known problems: "
                                  f"{', '.join(list_problems())}, or give a path to a .py script.")
        mod = importlib.import_module(f"stircasadi.problems.{key}")
    missing = [f for f in REQUIRED if not callable(getattr(mod, f, None))]
    if missing:
        raise StircasadiError(f"Problem {name_or_path!r} lacks {missing}; a problem script defines "
                              f"{', '.join(REQUIRED)} (and optionally NAME, truth(), ESTIMATE).")
    return mod


def problem_name(mod: ModuleType) -> str:
    return str(getattr(mod, "NAME", mod.__name__.rsplit(".", 1)[-1].removeprefix("_problem_")))


def problem_truth(mod: ModuleType) -> dict:
    """The problem's truth: its ``truth()`` when it defines one, else the scene's."""
    if callable(getattr(mod, "truth", None)):
        return mod.truth()
    return mod.build_scene().truth_dict()


def problem_main(mod: ModuleType, seed: int = 0) -> None:
    """What ``python problem.py`` does: simulate the problem through its sensor, print a summary."""
    from .transport import simulate

    scene, grid, sensor = mod.build_scene(), mod.build_grid(), mod.build_sensor()
    tr = simulate(scene, grid, sensor=sensor)
    cap = sensor.capture(tr, seed=seed)
    print(scene.describe())
    print(f"grid: {grid}; STIR {cap.stir.shape}; method={tr.metadata['method']}, "
          f"bounces={tr.metadata['bounces']}, omitted energy {tr.metadata.get('omitted_energy_rel', 0):.2e}")


if __name__ == "__main__":  # pragma: no cover
    problem_main(load_problem(sys.argv[1] if len(sys.argv) > 1 else None))
