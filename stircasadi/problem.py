"""Find and load problem scripts: a name in ``problems/`` or a path to a ``.py`` file.

A problem script is an importable factory module with ``build_scene()``, ``build_grid()``,
``build_sensor()``, ``truth()`` and ``main()`` (STYLE.md rule 9).
"""
from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from types import ModuleType

from .errors import StircasadiError

DEFAULT_PROBLEM = "hidden_corner"
REQUIRED = ("build_scene", "build_grid", "build_sensor")


def list_problems() -> list[str]:
    import problems

    folder = Path(problems.__file__).parent
    return sorted(p.stem for p in folder.glob("*.py") if not p.stem.startswith("_"))


def load_problem(name_or_path: str | None = None) -> ModuleType:
    """Import a problem by name (``problems.<name>``) or from a file path."""
    name_or_path = name_or_path or DEFAULT_PROBLEM
    path = Path(name_or_path)
    if path.suffix == ".py" or path.exists():
        if not path.exists():
            raise StircasadiError(f"Problem script not found: {path}.")
        spec = importlib.util.spec_from_file_location(f"_problem_{path.stem}", path)
        mod = importlib.util.module_from_spec(spec)
        try:
            spec.loader.exec_module(mod)
        except Exception as exc:
            raise StircasadiError(f"Problem script {path} failed to import: {exc}") from exc
    else:
        key = name_or_path.replace("-", "_")
        try:
            mod = importlib.import_module(f"problems.{key}")
        except ModuleNotFoundError as exc:
            raise StircasadiError(f"Unknown problem {name_or_path!r}; known problems: "
                                  f"{', '.join(list_problems())}, or give a path to a .py script.") from exc
    missing = [f for f in REQUIRED if not hasattr(mod, f)]
    if missing:
        raise StircasadiError(f"Problem {name_or_path!r} lacks {missing}; a problem script defines "
                              f"{', '.join(REQUIRED)} (and truth(), main()).")
    return mod
