"""Tiny numeric/symbolic dispatch so each physical formula is written once (STYLE.md rule 13).

Every function here takes NumPy arrays (or floats) or CasADi SX/MX/DM and returns the same kind.
Only elementwise operations are offered: physics formulas in stircasadi are written elementwise
in terms of distances, cosines and parameters.
"""
from __future__ import annotations

import numpy as np

try:  # casadi is a hard dependency, but keep the numeric path importable without it
    import casadi as ca
    _CA_TYPES = (ca.SX, ca.MX, ca.DM)
except ImportError:  # pragma: no cover
    ca = None
    _CA_TYPES = ()


def is_symbolic(*xs) -> bool:
    """True if any argument is a CasADi object."""
    return any(isinstance(x, _CA_TYPES) for x in xs)


def fmax(a, b):
    return ca.fmax(a, b) if is_symbolic(a, b) else np.maximum(a, b)


def fmin(a, b):
    return ca.fmin(a, b) if is_symbolic(a, b) else np.minimum(a, b)


def sqrt(a):
    return ca.sqrt(a) if is_symbolic(a) else np.sqrt(a)


def exp(a):
    return ca.exp(a) if is_symbolic(a) else np.exp(a)


def where(cond, a, b):
    if is_symbolic(cond, a, b):
        return ca.if_else(cond, a, b)
    return np.where(cond, a, b)


def power(a, p):
    """``a ** p`` for a >= 0 (p may be symbolic).

    Symbolically, ``0 ** p`` is guarded by ``if_else``: CasADi's derivative of ``a ** p`` with
    respect to p is ``a ** p * log(a)``, which is NaN at a = 0 (a Phong lobe outside its cone).
    """
    if is_symbolic(a, p):
        return ca.if_else(a > 0, a ** p, 0.0 * a)
    return np.power(a, p)
