"""Distances (T2) with eps: closed form and Monte Carlo coverage on the 3-patch problem."""
import numpy as np

from stircasadi.geometry import distances as dm
from stircasadi.geometry import onsets as on
from stircasadi.problem import load_problem
from stircasadi.irf import GaussianIRF
from stircasadi.sensor import GaussianNoise, Sensor
from stircasadi.transport import simulate


def test_forward_and_inverse_T2_closed_form():
    r = np.array([1.0, 1.2, 0.9])
    D = np.array([[0, 0.5, 0.7], [0.5, 0, 0.4], [0.7, 0.4, 0]])
    O = dm.forward_T2(r, D)
    sol = dm.solve_distances(np.arange(3), np.arange(3), O, np.full((3, 3), 1e-4))
    assert np.allclose(sol.D, D, atol=1e-12) and np.allclose(sol.r, r, atol=1e-12)
    # one missing pair: d stays unknown with an infinite bound, not a guess
    O[0, 2] = O[2, 0] = np.nan
    sol = dm.solve_distances(np.arange(3), np.arange(3), O, np.full((3, 3), 1e-4))
    assert np.isnan(sol.D[0, 2]) and np.isinf(sol.eps[0, 2])


def test_three_patch_eps_coverage_monte_carlo():
    """Stated noise: Gaussian sigma = 2e-5 (SNR of the second bounces ~ 20-25)."""
    mod = load_problem("three_patch")
    sc, g = mod.build_scene(), mod.build_grid()
    se = Sensor(irf=GaussianIRF.from_ps(210.0), noise=GaussianNoise(sigma=2e-5))
    tr = simulate(sc, g, sensor=se)
    Dt = sc.distances
    tm = None
    inside, total, z = 0, 0, []
    for seed in range(120):
        cap = se.capture(tr, seed=seed)
        tm = tm or on.make_template(cap)
        ill, obs, O, S, _ = on.second_onsets(cap, tm)
        sol = dm.solve_distances(ill, obs, O, S, level=0.99)
        for (a, b) in ((0, 1), (0, 2), (1, 2)):
            if np.isfinite(sol.D[a, b]):          # a weak second bounce may go undetected
                total += 1
                inside += abs(sol.D[a, b] - Dt[a, b]) <= sol.eps[a, b]
                z.append((sol.D[a, b] - Dt[a, b]) / sol.D_std[a, b])
    assert total >= 200
    rate = inside / total
    assert rate >= 0.96, rate
    assert 0.75 < np.std(z) < 1.3


def test_trusted_pairs_splits_two_snr_populations_only():
    """SNR-seeded embedding: a strong population (second bounces) and a weak one a decade below
    (intruding three-bounce families) split between them; one log-normal population does not
    split; a split that would leave a patch with < 4 trusted distances is refused."""
    from stircasadi.geometry.estimate import trusted_pairs

    rng = np.random.default_rng(8)
    M = 30
    ids = np.arange(M)
    weak = np.zeros((M, M), bool)
    weak[:15, :15] = weak[15:, 15:] = True          # two "planes": coplanar pairs are weak
    snr = np.where(weak, 10 ** rng.uniform(-0.3, 0.9, (M, M)), 10 ** rng.uniform(1.9, 3.5, (M, M)))
    snr = np.minimum(snr, snr.T)
    known = np.ones((M, M), bool)
    tr, thr = trusted_pairs(ids, ids, ids, snr, known)
    assert thr is not None and 10 ** 0.9 < thr < 10 ** 1.9
    off = ~np.eye(M, dtype=bool)
    np.testing.assert_array_equal(tr[off], ~weak[off])
    # one population: no split, everything trusted
    one = 10 ** rng.normal(2.5, 0.4, (M, M))
    tr1, thr1 = trusted_pairs(ids, ids, ids, np.minimum(one, one.T), known)
    assert thr1 is None and tr1[off].all()
    # a patch whose strong distances are all but 3 gone: the split is refused
    snr2 = snr.copy()
    snr2[0, 18:] = snr2[18:, 0] = 1.0
    tr2, thr2 = trusted_pairs(ids, ids, ids, snr2, known)
    assert thr2 is None
