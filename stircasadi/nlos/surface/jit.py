"""CasADi's JIT for the surface model's pair geometry (``model.SurfaceModel``).

When to use: ``SurfaceModel._build`` compiles its small SX functions through :func:`compiled`;
nothing else needs it. Compiled functions are cached per process by their serialised form (the
models of one fit, and its levels' first predictions, share them); where no compiler works the
function itself is used (same numbers, slower), and ``STIRCASADI_JIT=0`` turns compiling off.
"""
from __future__ import annotations

import casadi as ca

__all__ = ["compiled"]


#: the JIT's state for this process: its temporary folder, whether a compile failed (then every
#: later model uses the virtual machine without trying again), and the compiled functions by
#: their serialised form (the models of one fit, and its levels' first predictions, share them)
_JIT = {"dir": None, "unavailable": False, "done": {}}


def compiled(f: ca.Function) -> ca.Function:
    """``f`` compiled to machine code by CasADi's JIT (C through the system's compiler, -O2, no
    fast-math: the same IEEE arithmetic; the map over (trace, node) pairs then runs 3-4x faster
    than CasADi's SX virtual machine), or ``f`` itself where no compiler works (the result is the
    same, only slower) or when the environment sets STIRCASADI_JIT=0."""
    import os
    if os.environ.get("STIRCASADI_JIT", "1") == "0" or _JIT["unavailable"]:
        return f
    key = f.serialize()
    if key in _JIT["done"]:
        return _JIT["done"][key]
    try:
        if _JIT["dir"] is None:
            import atexit
            import shutil
            import tempfile
            _JIT["dir"] = tempfile.mkdtemp(prefix="stircasadi-jit-")
            atexit.register(shutil.rmtree, _JIT["dir"], True)
        ins = f.sx_in()
        fc = ca.Function(f.name(), ins, f.call(ins), {
            "jit": True, "compiler": "shell", "jit_temp_suffix": True, "jit_cleanup": False,
            "jit_options": {"flags": ["-O2"], "directory": _JIT["dir"], "cleanup": False}})
    except Exception as exc:                        # no compiler, unwritable temp folder, ...
        import logging
        logging.getLogger(__name__).info("CasADi JIT unavailable (%s); the pair geometry runs on "
                                         "CasADi's virtual machine (same numbers, slower)", exc)
        _JIT["unavailable"] = True
        return f
    _JIT["done"][key] = fc
    return fc
