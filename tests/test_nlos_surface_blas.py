"""The surface model's Gram products (``nlos/surface/blas.py``): syrk called without the GIL
equals SciPy's wrapper bit for bit and J^T J to rounding, its fallback gives the same numbers,
the BLAS thread limit holds inside its context only, and a linearisation whose syrk runs on one
BLAS thread (workers > 1) equals the one on the library's own threads."""
import numpy as np
import pytest
from scipy.linalg import blas as sblas

from stircasadi.nlos.surface import blas as gb


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_gram_lower_is_scipys_syrk_bit_for_bit_and_j_transpose_j(dtype, monkeypatch):
    rng = np.random.default_rng(3)
    J = rng.standard_normal((301, 97)).astype(dtype)
    L = gb.gram_lower(J)
    assert L.flags.c_contiguous and L.dtype == dtype
    ref = (sblas.ssyrk if dtype == np.float32 else sblas.dsyrk)(1.0, J.T, trans=0, lower=0)
    assert np.array_equal(np.tril(L), np.tril(ref.T))
    exact = J.astype(np.float64).T @ J.astype(np.float64)
    tol = 1e-4 if dtype == np.float32 else 1e-12
    assert np.allclose(np.tril(L), np.tril(exact), rtol=tol, atol=tol * np.abs(exact).max())
    # the fallback (another SciPy build: no cython_blas pointer) gives the same numbers
    monkeypatch.setattr(gb, "_SYRK", {np.dtype(dtype).char: None})
    assert np.array_equal(np.tril(gb.gram_lower(J)), np.tril(L))


def test_blas_threads_limits_inside_its_context_only():
    import threadpoolctl       # a dependency (pyproject.toml)

    def blas_threads_now():
        return [d["num_threads"] for d in threadpoolctl.threadpool_info() if d["user_api"] == "blas"]

    before = blas_threads_now()
    if not before:
        pytest.skip("no BLAS library that threadpoolctl can see")
    with gb.blas_threads(1):
        inside = blas_threads_now()
    assert inside == [1] * len(before) and blas_threads_now() == before
    with gb.blas_threads(None):         # None: nothing changes
        assert blas_threads_now() == before


def test_linearise_on_one_blas_thread_equals_the_librarys_threads():
    """Two chunks of 1 200 rows x 804 columns (syrks the library splits over its threads):
    ``workers=2`` runs them on two threads, each syrk on one BLAS thread without the GIL,
    ``workers=1`` one after the other through the library's own threads; float32 Gram (the
    solver's), the same bits."""
    from stircasadi.nlos.relay import Relay
    from stircasadi.nlos.surface.grid import DepthGrid
    from stircasadi.nlos.surface.model import SurfaceModel, SurfaceState
    from stircasadi.nlos.surface.response import Response
    from stircasadi.timegrid import TimeGrid
    rng = np.random.default_rng(5)
    frame = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))
    grid = DepthGrid(np.linspace(-0.2, 0.2, 20), np.linspace(-0.2, 0.2, 20), frame)
    P, T = 8, 300
    L = np.c_[rng.uniform(-0.3, 0.3, (P, 2)), np.zeros(P)]
    n = np.tile([0, 0, 1.0], (P, 1))
    rl = Relay(np.zeros((P, T)), TimeGrid(0.5, 0.004, T), L, L, n, n, 0.0, 1.0)
    resp = Response("emg", 0.006, 0.01, ((0.03, 0.3),))
    st = SurfaceState(0.4 + 0.02 * rng.standard_normal(grid.n), rng.uniform(0.3, 1, grid.n), 0.006, 0.01, (0.3,), 0.01)
    out = {}
    for workers in (1, 2):
        per = T * 7 * grid.n * 4 * 2        # linearise's bytes per trace (float32, slow tails)
        model = SurfaceModel(grid, rl, resp, "lambertian", workers=workers, chunk_bytes=4 * per)
        assert len(list(model._chunks(per))) == 2
        if workers == 1:
            y = model.predict(st) + 1e-3 * rng.standard_normal((P, T))
            wgt = rng.uniform(0.5, 2, (P, T))
        out[workers] = model.linearise(st, y, wgt, dtype=np.float32)
    assert out[1]["H"].shape == (model.npar, model.npar) and model.npar > 800 and np.abs(out[1]["H"]).max() > 0
    for k in ("m", "g", "H"):
        assert np.array_equal(out[1][k], out[2][k]), k
