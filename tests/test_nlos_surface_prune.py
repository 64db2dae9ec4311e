"""Nodes the data give no evidence of (step 4b of ``nlos/surface/fit.py``, ``prune.py``): the
evidence is the exact chi^2 rise without the node, off-surface nodes are pruned and the surface
kept, and faint nodes that together explain the data are not pruned."""
import numpy as np
import pytest

from stircasadi.nlos.relay import Relay
from stircasadi.nlos.surface.grid import DepthGrid
from stircasadi.nlos.surface.lm import Bounds, solve_lm
from stircasadi.nlos.surface.model import SurfaceModel, SurfaceState
from stircasadi.nlos.surface.prune import PRUNE_P, node_evidence, prune_nodes
from stircasadi.nlos.surface.response import Response
from stircasadi.timegrid import TimeGrid


def _small(rng, n_traces=12):
    """A 4 x 3 grid at 0.4 m over a paired relay of ``n_traces`` random pairs (Gaussian response
    6 mm)."""
    frame = (np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.array([0, 0, 1.0]))
    grid = DepthGrid(np.linspace(-0.1, 0.1, 4), np.linspace(-0.1, 0.1, 3), frame)
    L = np.c_[rng.uniform(-0.2, 0.2, (n_traces, 2)), np.zeros(n_traces)]
    D = np.c_[rng.uniform(-0.2, 0.2, (n_traces, 2)), np.zeros(n_traces)]
    n = np.tile([0, 0, 1.0], (n_traces, 1))
    rl = Relay(np.zeros((n_traces, 150)), TimeGrid(0.6, 0.004, 150), L, D, n, n, 0.0, 1.0)
    return SurfaceModel(grid, rl, Response("gaussian", 0.006), fit_shape=False)


def test_the_evidence_is_the_exact_chi2_rise_without_the_node():
    """node_evidence (rho^2 H_ii - 2 rho g_i from one linearisation) against chi^2 evaluated
    with each node's albedo set to zero in turn, at a state off the optimum (the gradient term
    matters): equal to rounding, the model being linear in the albedos."""
    rng = np.random.default_rng(5)
    model = _small(rng)
    N = model.N
    st = SurfaceState(0.4 + 0.01 * rng.standard_normal(N), rng.uniform(0.1, 1, N), 0.006, 0.0, (), 0.0)
    y = model.predict(SurfaceState(st.z, rng.uniform(0.1, 1, N), 0.006, 0.0, (), 0.0))
    y += 1e-3 * rng.standard_normal(y.shape)
    wgt = np.full(y.shape, 1e4)
    lin = model.linearise(st, y, wgt, dtype=np.float64)
    ev = node_evidence(st.rho, lin["g"][N:2 * N], np.diag(lin["H"])[N:2 * N])
    c0 = model.objective(st, y, wgt)[0]
    exact = np.array([model.objective(SurfaceState(st.z, np.where(np.arange(N) == i, 0.0, st.rho), 0.006,
                                                   0.0, (), 0.0), y, wgt)[0] - c0 for i in range(N)])
    assert np.all(np.abs(ev - np.maximum(exact, 0)) <= 1e-9 * np.abs(exact).max())
    curv = st.rho ** 2 * np.diag(lin["H"])[N:2 * N]     # without the gradient term: off
    assert np.max(np.abs(curv - exact)) > 0.1 * np.abs(exact).max()


def _fit_and_prune(model, y, wgt, st0, worse: float = 0.0):
    """LM from ``st0`` to the optimum, then ``prune_nodes`` with the solver and bounds the fit uses
    (``worse``: added to the pruned solve's F)."""
    held = {"m": np.zeros(model.N, bool)}

    def make_bounds(m):
        b = Bounds(m, 1.0, (0.001, 0.05), (0.0, 0.1))
        b.hi[m.N:2 * m.N][held["m"]] = 0.0
        return b

    R = np.zeros((model.N, model.N))

    def solve(m, b, s):
        return solve_lm(m, y, wgt, s, 0.0, R, b, 0.01, 60, 1e-12, np.float64)

    res = solve(model, make_bounds(model), st0)
    if worse:
        first = solve

        def solve(m, b, s):
            out = first(m, b, s)
            return out | {"f": out["f"] + worse}
    lin = model.linearise(res["state"], y, wgt, dtype=np.float64)
    out = prune_nodes(res["state"], res, lin, y, wgt, model, lambda m: held.__setitem__("m", m), make_bounds, solve)
    return res, out, held["m"]


def _three_lit():
    """The small model with nodes 4, 5, 7 lit (albedo 0.8), the others dark, at 0.1 % noise:
    (model, lit, depths, data, weights)."""
    rng = np.random.default_rng(11)
    model = _small(rng)
    lit = np.zeros(model.N, bool)
    lit[[4, 5, 7]] = True
    z = 0.4 + 0.01 * rng.standard_normal(model.N)
    clean = model.predict(SurfaceState(z, np.where(lit, 0.8, 0.0), 0.006, 0.0, (), 0.0))
    sig = 1e-3 * clean.max()
    y = clean + sig * rng.standard_normal(clean.shape)
    return model, lit, z, y, np.full(y.shape, 1.0 / sig ** 2)


def test_nodes_off_the_surface_are_pruned_and_the_surface_stays():
    """Three lit nodes (albedo 0.8) and nine of zero albedo, 0.1 % noise: fitted from albedos
    0.05 on the dark nodes, the dark nodes fit noise; every one of them whose fitted albedo
    explains less than the chi^2(2) quantile at 0.01 (9.21) is pruned (measured: all nine), none of
    the lit ones is, the pruned model is kept (its likelihood ratio against the full model below
    the threshold of the unknowns removed) and its solve ends with the pruned albedos at zero and
    the lit ones within 3 std of the truth (measured: nine pruned, five of them lit, the largest
    evidence 5.4; likelihood ratio 11.6 against the chi^2(5) quantile 15.1)."""
    model, lit, z, y, wgt = _three_lit()
    N = model.N
    res, out, held = _fit_and_prune(model, y, wgt, SurfaceState(z.copy(), np.where(lit, 0.7, 0.05), 0.006, 0.0, (), 0.0))
    info = out["info"]
    assert info["kept"] and info["lr"] <= info["threshold"] and info["p"] == PRUNE_P
    assert not held[lit].any() and held[~lit].all()
    s = out["res"]["state"]
    assert np.all(s.rho[held] == 0.0)
    H = model.linearise(s, y, wgt, dtype=np.float64)["H"]
    free = np.r_[np.flatnonzero(model.seen(s.rho)), N + np.flatnonzero(~held)]
    C = np.linalg.pinv(H[np.ix_(free, free)])
    rho_std = np.sqrt(np.diag(C))[-lit.sum():]
    assert np.all(np.abs(s.rho[lit] - 0.8) < 3 * rho_std)


def test_the_full_model_stands_when_the_pruned_one_fits_worse_than_chance_allows():
    """The rule's other branch, on the scene above: the pruned model's solve made to end 50
    above the full one in F (chi^2 + 100, as if the pruned nodes had explained signal together):
    the likelihood ratio, 100 over the inflation, exceeds the chi^2 quantile of the unknowns
    removed at p = 0.01, so the pruned model is not kept, the hold is released and the bounds
    returned free again."""
    model, lit, z, y, wgt = _three_lit()
    N = model.N
    res, out, held = _fit_and_prune(model, y, wgt, SurfaceState(z.copy(), np.where(lit, 0.7, 0.05), 0.006, 0.0, (), 0.0),
                                    worse=50.0)
    info = out["info"]
    infl = max(1.0, model.objective(out["res"]["state"], y, wgt)[0] / (y.size - model.npar))
    assert info["nodes"] == 9 and info["lr"] >= 100.0 / infl     # measured 111.1: 11.6 of its own
    assert info["lr"] > info["threshold"] and not info["kept"]
    assert not held.any() and not out["mask"].any() and np.all(out["bounds"].hi[N:2 * N] == 1.0)


def test_nested_likelihood_ratio_by_hand():
    """``nested_lr``: 2 (F_restricted - F_general) over the general model's inflation, against the
    chi^2 quantile of the removed unknowns: F 10 against 4 with chi2/dof 3 gives 4; at chi2/dof
    below 1 no deflation (12); the threshold of 2 unknowns at p = 0.01 is -2 ln 0.01 = 9.2103."""
    from stircasadi.nlos.surface.lm import nested_lr
    lr, need = nested_lr(10.0, 4.0, 300.0, 100, 2, 0.01)
    assert lr == pytest.approx(4.0, rel=1e-15) and need == pytest.approx(-2 * np.log(0.01), rel=1e-12)
    lr, need = nested_lr(10.0, 4.0, 50.0, 100, 1, 0.05)
    assert lr == pytest.approx(12.0, rel=1e-15) and need == pytest.approx(3.841459, rel=1e-6)


@pytest.mark.parametrize("first_iterations", [3, 4])
def test_an_early_stopped_pruned_solve_decides_as_a_finished_one(first_iterations):
    """``prune_nodes(early=True)`` (step 4b with step 4c to follow): the pruned solve stops
    ("Target reached") once its F is as low as the full solve's, where that solve stopped at its
    iteration limit short of its optimum (3 iterations from depths 2 mm off and albedos 0.5 / 0.1:
    F 894.7; the pruned optimum 888.6 lies below it); the ratio is then at most 0 and only falls
    as the solve goes on, so the decision is the finished pruned solve's (kept, the same nodes), in
    fewer iterations (measured 1 against 15), and the solve continued from where it stopped ends
    at the finished solve's F. After 4 iterations the full solve's F (886.9) is below the pruned
    optimum: the early solve never reaches it and is the finished one (settled, the same F)."""
    model, lit, z, y, wgt = _three_lit()
    st0 = SurfaceState(z.copy() + 0.002, np.where(lit, 0.5, 0.1), 0.006, 0.0, (), 0.0)
    R = np.zeros((model.N, model.N))
    outs, helds = {}, {}
    for early in (False, True):
        held = {"m": np.zeros(model.N, bool)}

        def make_bounds(m, held=held):
            b = Bounds(m, 1.0, (0.001, 0.05), (0.0, 0.1))
            b.hi[m.N:2 * m.N][held["m"]] = 0.0
            return b

        def solve(m, b, s, f_stop=None, it=60):
            return solve_lm(m, y, wgt, s, 0.0, R, b, 0.01, it, 1e-12, np.float64, f_stop=f_stop)

        res = solve(model, make_bounds(model), st0, it=first_iterations)
        assert res["status"].startswith("Maximum")
        lin = model.linearise(res["state"], y, wgt, dtype=np.float64)
        outs[early] = prune_nodes(res["state"], res, lin, y, wgt, model, lambda m, h=held: h.__setitem__("m", m),
                                  make_bounds, solve, early=early)
        helds[early] = held["m"].copy()
    full, out = outs[False]["info"], outs[True]["info"]
    assert full["kept"] and out["kept"] and np.array_equal(helds[True], helds[False]) and helds[True].any()
    assert full["settled"] and out["lr"] <= out["threshold"]
    if first_iterations == 3:
        assert out["status"] == "Target reached" and not out["settled"]
        assert out["iterations"] < full["iterations"] and out["lr"] <= 0.0
        on = solve_lm(model, y, wgt, outs[True]["res"]["state"], 0.0, R, outs[True]["bounds"], 0.01, 60, 1e-12,
                      np.float64)
        assert on["f"] == pytest.approx(outs[False]["res"]["f"], rel=1e-9)
    else:
        assert out["settled"] and out["iterations"] == full["iterations"]
        assert outs[True]["res"]["f"] == outs[False]["res"]["f"]
