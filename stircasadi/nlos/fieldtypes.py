"""The kinds of value a settings dataclass's fields take, checked before their ranges are.

When to use: first in ``VolumeSettings.validate`` and ``SurfaceSettings.validate``; options come
from scripts and from ``--nlos KEY=VALUE``, where a mistyped value arrives as text (``n_nodes=abc``
was an internal error, ``int()`` or ``<`` failing on a string, instead of a message naming what
the field takes).

Each field's annotation (a string under ``from __future__ import annotations``) is read as
alternatives separated by ``|``: ``int`` takes a whole number (an integral float too), ``float``
any real number (not a bool), ``bool`` a bool or 0 / 1, ``str`` text, ``tuple`` a tuple, list or array,
``None`` None. A field whose annotation names anything else is not checked here.
"""
from __future__ import annotations

import numbers
from dataclasses import fields

import numpy as np

from ..errors import ReconstructionError

__all__ = ["check_field_types"]

_WORDS = {"int": "a whole number", "float": "a number", "bool": "true or false", "str": "text",
          "tuple": "a list", "None": "None (null)"}


def _takes(kind: str, v) -> bool:
    if kind == "None":
        return v is None
    if kind == "bool":
        return isinstance(v, (bool, np.bool_)) or (isinstance(v, numbers.Integral) and int(v) in (0, 1))
    if kind == "str":
        return isinstance(v, str)
    if kind == "tuple":
        return isinstance(v, (tuple, list, np.ndarray))
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        return False
    return kind == "float" or float(v).is_integer()


def check_field_types(obj, what: str) -> None:
    """Raise ``ReconstructionError`` naming the first field of the dataclass ``obj`` whose value
    is of a kind its annotation does not allow (``what``: the class's name, for the message)."""
    for f in fields(obj):
        kinds = [k.strip() for k in str(f.type).split("|")]
        if not kinds or any(k not in _WORDS for k in kinds):
            continue
        v = getattr(obj, f.name)
        if not any(_takes(k, v) for k in kinds):
            allowed = " or ".join(_WORDS[k] for k in kinds)
            raise ReconstructionError(f"{what}.{f.name} must be {allowed}; got {v!r} ({type(v).__name__}).")
