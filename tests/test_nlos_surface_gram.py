"""A linearisation with dark nodes (``nlos/surface/gram.py`` and ``SurfaceModel.linearise``):
the window bins of a zero albedo get no patch derivatives (they carry the albedo as a factor),
so only the lit bins enter the depth columns' sparse product. The gradient and Gauss-Newton
matrix must still be those of central differences of ``predict``, the dark nodes' own columns
included: a dark node's albedo column is its pairs' kernel, and its depth moves its lit
neighbours' normals."""
import numpy as np
import pytest

from nlos_twins import linearise_against_fd
from stircasadi.nlos.relay import Relay
from stircasadi.nlos.surface.grid import DepthGrid
from stircasadi.nlos.surface.model import SurfaceModel, SurfaceState
from stircasadi.nlos.surface.response import Response
from stircasadi.timegrid import TimeGrid

FRAME = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))


@pytest.mark.parametrize("kind, slow, sub, wide, offs", [("gaussian", (), 1, False, False),
                                                         ("emg", ((0.04, 0.3),), 2, False, True),
                                                         ("gaussian", ((0.04, 0.3),), 1, True, True),
                                                         ("emg", (), 2, True, False)])
def test_dark_nodes_linearise_like_finite_differences(kind, slow, sub, wide, offs, monkeypatch):
    """A 4 x 3 grid with three albedos exactly zero (node 1 among lit neighbours, nodes 6 and 7
    side by side), five paired traces: g = J^T W r and H = J^T W J against central differences
    of ``predict`` for every unknown (the core's tail too where it is an EMG), float64; the dark
    node 1's depth column is not empty (its neighbours' central differences hold it) and its
    albedo column is its kernel's. ``wide``: a 10 x 3 grid whose last four columns are dark too,
    so the depth columns of the last three lie beyond every lit node's stencil (which reaches one
    node): they are left out of the chunks' Gram products (``zkeep``) and come back as exact
    zeros. ``offs``: nodes 0 and 11 (lit) and 6 (dark) with a free centroid offset each."""
    import stircasadi.nlos.surface.model as sm
    seen = []

    def spy(*a, **kw):
        seen.append(a[-1])
        return real(*a, **kw)
    real = sm.chunk_gram
    monkeypatch.setattr(sm, "chunk_gram", spy)
    rng = np.random.default_rng(11)
    grid = DepthGrid(np.linspace(-0.1, 0.1 + 0.2 * wide, 10 if wide else 4), np.linspace(-0.1, 0.1, 3), FRAME)
    L = np.c_[rng.uniform(-0.2, 0.2, (5, 2)), np.zeros(5)]
    D = np.c_[rng.uniform(-0.2, 0.2, (5, 2)), np.zeros(5)]
    n = np.tile([0, 0, 1.0], (5, 1))
    rl = Relay(np.zeros((5, 150)), TimeGrid(0.6, 0.004, 150), L, D, n, n, 0.0, 1.0)
    tail = 0.01 if kind == "emg" else 0.0
    model = SurfaceModel(grid, rl, Response(kind, 0.006, tail, slow), "lambertian", subsamples=sub,
                         offset_nodes=[0, 6, 11] if offs else None)
    rho = rng.uniform(0.3, 1, grid.n)
    dark = [1, 6, 7] + ([k for k in range(grid.n) if k % 10 >= 6] if wide else [])
    rho[dark] = 0.0
    st = SurfaceState(0.4 + 0.02 * rng.standard_normal(grid.n), rho, 0.006, tail, tuple(b for _, b in slow), 0.01,
                      off=rng.uniform(-0.02, 0.02, (3, 2)) if offs else None)
    lin, H_fd = linearise_against_fd(model, st, rng, (5, 150))
    N = grid.n
    assert H_fd[1, 1] > 1e-3 * np.median(np.diag(H_fd)[:N])                 # dark node 1's depth
    assert np.all(np.diag(lin["H"])[N:2 * N][dark] > 0)                      # the dark nodes' albedos
    if offs:     # the offsets' columns (nodes 0, 6, 11): the dark node's are zero, the lit ones' not
        d = np.diag(lin["H"])[-6:]
        assert np.all(d[[0, 1, 4, 5]] > 0) and not np.any(lin["H"][-4:-2]) and not np.any(H_fd[-4:-2])
    out = [k for k in range(N) if k % 10 >= 7] if wide else []
    assert (seen[0] is None) == (not wide)
    if wide:              # the depth columns left out: those of the nodes beyond every lit stencil
        assert list(np.setdiff1d(np.arange(N), seen[0])) == out
        assert not np.any(lin["H"][out]) and not np.any(H_fd[out])
