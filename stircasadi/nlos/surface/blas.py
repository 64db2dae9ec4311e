"""The surface model's Gram products on worker threads: BLAS syrk without the GIL, one BLAS
thread per worker.

When to use: ``SurfaceModel.linearise`` forms each trace chunk's J^T W J through
:func:`gram_lower` and runs its chunks inside :func:`blas_threads`; nothing else needs them.

Why: SciPy's ``scipy.linalg.blas`` wrappers hold the GIL for the whole BLAS call, so while one
worker's syrk ran (a tenth of a linearisation at 32 x 32 nodes) the other worker could not
start any NumPy call; and OpenBLAS ran each syrk on all cores on top of the workers. The same
routine of the same library is called here through ``scipy.linalg.cython_blas``'s function
pointer by ctypes (which releases the GIL), with the BLAS libraries held to one thread while
the workers run (threadpoolctl). The numbers are the same bit for bit (the same routine and
arguments; syrk splits its output, not its sums, over threads): on the 40 cm resolution chart's
first 32 x 32 linearisation, 2 workers, 5.0-5.3 s before and 4.1-4.5 s after, H, g and the
model identical (``benchmarks/nlos.py --surface 32``, BENCHMARKS.md).
Where either part is unavailable (another SciPy build, no threadpoolctl), the wrapper and the
library's own threads are used: the same numbers, slower.
"""
from __future__ import annotations

import contextlib
import ctypes

import numpy as np

__all__ = ["gram_lower", "blas_threads"]

#: ctypes callables of cython_blas's ssyrk / dsyrk (None: not available, use scipy.linalg.blas)
_SYRK: dict = {}
#: threadpoolctl's controller, made once (it inspects the process's loaded libraries)
_POOL: dict = {}


def _syrk(dtype):
    """The ctypes callable of BLAS ?syrk for ``dtype`` (float32 / float64), or None."""
    key = np.dtype(dtype).char
    if key not in _SYRK:
        try:
            from scipy.linalg import cython_blas
            api = ctypes.pythonapi
            api.PyCapsule_GetName.restype = ctypes.c_char_p
            api.PyCapsule_GetName.argtypes = [ctypes.py_object]
            api.PyCapsule_GetPointer.restype = ctypes.c_void_p
            api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
            cap = cython_blas.__pyx_capi__["ssyrk" if key == "f" else "dsyrk"]
            ptr = api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap))
            ip, vp = ctypes.POINTER(ctypes.c_int), ctypes.c_void_p
            proto = ctypes.CFUNCTYPE(None, ctypes.c_char_p, ctypes.c_char_p, ip, ip, vp, vp, ip, vp, vp, ip)
            _SYRK[key] = (proto(ptr), ctypes.c_float if key == "f" else ctypes.c_double)
        except Exception:                                   # another SciPy build: the wrapper
            _SYRK[key] = None
    return _SYRK[key]


def gram_lower(J: np.ndarray) -> np.ndarray:
    """The lower triangle of J^T J, C-ordered, by the symmetric rank-k update (BLAS syrk: half
    the products of a general matrix product), in J's precision (float32 or float64); the upper
    triangle holds no meaning. The caller adds it into a C-ordered sum: both arrays are then
    read in memory order."""
    J = np.ascontiguousarray(J)
    fn = _syrk(J.dtype) if J.dtype in (np.float32, np.float64) else None
    if fn is None:
        from scipy.linalg import blas
        f = blas.ssyrk if J.dtype == np.float32 else blas.dsyrk
        return f(1.0, J.T, trans=0, lower=0).T    # J.T is Fortran-ordered; syrk's upper, transposed
    call, ct = fn
    k, n = J.shape
    C = np.zeros((n, n), J.dtype)
    one, zero = ct(1.0), ct(0.0)
    nn, kk = ctypes.c_int(n), ctypes.c_int(k)
    vp = ctypes.c_void_p
    # column-major view: J's memory is J^T (n x k, lda n) and C's is C^T; "U", "N": the upper
    # triangle of J^T (J^T)^T in column-major order, which is C's lower triangle in C order
    call(b"U", b"N", ctypes.byref(nn), ctypes.byref(kk), ctypes.cast(ctypes.pointer(one), vp), J.ctypes.data_as(vp),
         ctypes.byref(nn), ctypes.cast(ctypes.pointer(zero), vp), C.ctypes.data_as(vp), ctypes.byref(nn))
    return C


def blas_threads(limit: int | None):
    """A context in which the BLAS libraries run ``limit`` threads (None: unchanged), through
    threadpoolctl where it is installed (else a no-op)."""
    if limit is None:
        return contextlib.nullcontext()
    if "ctl" not in _POOL:
        try:
            from threadpoolctl import ThreadpoolController
            _POOL["ctl"] = ThreadpoolController()
        except Exception:                                   # not installed, or no BLAS found
            _POOL["ctl"] = None
    ctl = _POOL["ctl"]
    return contextlib.nullcontext() if ctl is None else ctl.limit(limits=int(limit), user_api="blas")
