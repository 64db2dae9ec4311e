"""General (tabulated) BRDF f_kij with Helmholtz reciprocity and energy as NLP constraints."""
from __future__ import annotations

import math

import numpy as np

from stircasadi.problems import three_patch
from stircasadi.joint import JointNLP
from stircasadi.joint.fit import fit_model
from stircasadi.model import TransientModel

from _reflectance_helpers import capture_of, quiet


def test_general_form_factors_reproduce_lambertian_and_keep_reciprocity():
    sc, gr, se, tr, cap = capture_of(three_patch, seed=2)
    m = TransientModel.from_scene(sc, gr, se.irf).set_general_brdf("all").setup()
    T = m.triples
    assert len(T) > 3 and set(T[:, 0]) >= {-1} and set(T[:, 2]) >= {-2}
    f_true = sc.albedos[T[:, 1]] / math.pi
    y = m.simulate(m.x_of({"fkij": f_true}))
    assert np.abs(y - tr.stir).max() / tr.stir.max() < 1e-9
    nlp = JointNLP(m, cap.stir, quiet(), noise=cap.noise)
    n_rec = sum(1 for nm in nlp.g_names if nm.startswith("reciprocity"))
    assert n_rec >= 3
    e = fit_model(m, cap.stir, quiet(), noise=cap.noise)
    assert e.success
    g = np.asarray(nlp.f_g(e.x)).ravel()
    rec = np.array([k for k, nm in enumerate(nlp.g_names) if nm.startswith("reciprocity")])
    assert np.abs(g[rec]).max() < 1e-7  # hard constraint, not a penalty
    # the data are fitted to the noise: chi^2 per support bin ~ 1
    assert 0.7 < 2 * e.extra["cost"] / len(nlp.y) < 1.3
    # f_kij of the first bounce (source -> i -> camera) is identified: rho_i / pi
    fb = np.array([k for k, (a, i, b) in enumerate(T.tolist()) if a == -1 and b == -2])
    got = e.values["fkij"][fb]
    assert np.all(np.abs(got - f_true[fb]) < 4 * e.std["fkij"][fb] + 1e-12)
