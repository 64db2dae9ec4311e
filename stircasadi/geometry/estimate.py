"""``estimate_geometry``: the geometry stage from a Capture (see the package docstring).

Full STIR with legs included -> onsets -> T2 distances (+eps) -> positions (the capture's
visible points when it knows them, else MDS + bounded IPOPT refinement) -> normals and plane
groups -> hidden patches from third onsets (robust labeling) -> a check that the placed hidden
patches explain every return that only a hidden surface can produce (else an
``unexplained-hidden-returns`` ambiguity: an extended hidden surface whose returns blend).
Rectified relay-wall / confocal captures go to ``relay.estimate_relay``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..errors import GeometryError, SolverError
from . import distances as dm
from . import embedding as em
from . import hidden as hm
from . import normals as nm
from . import onsets as on
from .result import GeometryEstimate, StageStats


@dataclass
class GeometrySettings:
    """Settings of the geometry stage."""

    #: two-sided confidence of the eps bounds
    eps_level: float = 0.99
    #: onset model-error allowance added (in quadrature) to every onset std, in bins
    onset_floor_bins: float = 0.01
    #: detection threshold (noise standard deviations of the matched filter)
    k_sigma: float = 6.0
    #: onset fit window: IRF widths after the peak
    right_sigmas: float = 1.5
    #: refine positions with the bounded-error IPOPT problem
    refine: bool = True
    #: labeling of hidden returns: "robust" or "paper"
    hidden_method: str = "robust"
    #: most third-onset families searched per trace
    max_third: int = 6
    #: Gaussian IRF FWHM (metres of path) when the capture has no irf (None: estimate)
    irf_fwhm: float | None = None
    #: a distance whose residual exceeds this many std at the fitted positions is an outlier
    outlier_z: float = 8.0
    #: refinement bounds hold jointly at eps_level (Bonferroni over the n bounded distances:
    #: each at 1 - (1 - eps_level) / n); False: each at eps_level, so ~n (1 - eps_level) of them
    #: exclude the truth and the bounded problem distorts or widens
    joint_bounds: bool = True
    #: least separation (decades) of the two onset-SNR populations for SNR-seeded embedding
    snr_split_decades: float = 0.5

    def validate(self) -> "GeometrySettings":
        if not 0 < self.eps_level < 1:
            raise GeometryError(f"eps_level must be in (0, 1); got {self.eps_level!r}.")
        if self.hidden_method not in ("robust", "paper"):
            raise GeometryError(f"hidden_method must be 'robust' or 'paper'; got {self.hidden_method!r}.")
        return self


def _forget_pairs(sol, pairs) -> None:
    """Mark the distances of ``pairs`` (index pairs into sol.ids) unknown: NaN, infinite std/eps."""
    for a, b in pairs:
        sol.D[a, b] = sol.D[b, a] = np.nan
        sol.D_std[a, b] = sol.D_std[b, a] = np.inf
        sol.eps[a, b] = sol.eps[b, a] = np.inf


def trusted_pairs(ids, ill, obs, snr, known, min_decades: float = 0.5, min_degree: int = 4):
    """Pairs whose second onsets are strong returns: (trusted (M, M) bool, threshold or None).

    A second bounce i -> j carries one form factor less than any three-bounce family, so where
    a pair has no second bounce (coplanar patches, an occluder between them) the earliest family
    detected in its trace is a return that is typically 10-1000x weaker. When the off-diagonal
    onset SNRs (the weaker of O2_ij, O2_ji) split into two populations whose nearest members
    are at least ``min_decades`` decades apart (the largest gap of the sorted log-SNR, between
    two populations of at least 5 % each), the upper one is trusted to seed the embedding.
    Nothing is dropped here: the caller keeps a weak pair when it agrees with the seeded
    geometry. No split (threshold None, all trusted) when there is no such gap, or when some
    patch would keep fewer than ``min_degree`` trusted distances.
    """
    ids = np.asarray(ids)
    M = len(ids)
    pos = {int(v): k for k, v in enumerate(ids)}
    P = np.full((M, M), np.inf)
    for a, i in enumerate(ill):
        for b, j in enumerate(obs):
            i_, j_ = int(i), int(j)
            if i_ != j_ and i_ in pos and j_ in pos and np.isfinite(snr[a, b]):
                x, y = pos[i_], pos[j_]
                P[x, y] = P[y, x] = min(P[x, y], float(snr[a, b]))
    all_known = np.asarray(known, bool).copy()
    np.fill_diagonal(all_known, False)
    vals = P[np.triu(all_known & np.isfinite(P), 1)]
    vals = vals[vals > 0]
    if len(vals) < 20:
        return all_known, None
    ls = np.sort(np.log10(vals))
    n = len(ls)
    lo_k, hi_k = max(int(0.05 * n), 1), min(int(0.95 * n), n - 1)
    gaps = ls[lo_k:hi_k] - ls[lo_k - 1:hi_k - 1]
    k = int(np.argmax(gaps))
    if gaps[k] < min_decades:
        return all_known, None
    thr = float(10 ** (0.5 * (ls[lo_k - 1 + k] + ls[lo_k + k])))
    trusted = all_known & np.isfinite(P) & (P >= thr)
    if trusted.sum(axis=1).min() < min_degree:
        return all_known, None
    return trusted, thr


def shortest_visible_walks(D: np.ndarray) -> np.ndarray:
    """(M, M) length of the shortest path i -> k -> ... -> j with at least two edges in the graph
    whose edges are the measured second-bounce distances (patches that see each other): the
    earliest return of three or more bounces through visible patches only (Floyd-Warshall)."""
    M = len(D)
    Dk = np.where(np.isfinite(D), D, np.inf)
    np.fill_diagonal(Dk, np.inf)
    SP = Dk.copy()
    for k in range(M):
        SP = np.minimum(SP, SP[:, k:k + 1] + SP[k:k + 1, :])
    late = np.empty((M, M))
    for a in range(M):
        late[a] = np.min(Dk[a][:, None] + SP, axis=0)
    return late


def unexplained_hidden_returns(third: dict, ids, X, D, r, c, hid_pos, W: float, margin: float = 2.0) -> dict:
    """Traces holding a family that only a hidden surface can produce, and how many of them the
    placed hidden patches do not explain.

    In trace (i, j) a family at excess path e = tau - r_i - c_j with
    early_ij + margin W < e < late_ij - margin W, where early is the first (i = j) or the second
    bounce (d_ij; |x_i - x_j| when the two do not see each other) and late the shortest visible
    walk of two or more edges (``shortest_visible_walks``), can only come via a hidden point
    (every visible path of three or more bounces takes at least ``late``). It is explained when
    it lies within margin W of |x_i - h| + |h - x_j| for a placed hidden patch h."""
    ids = np.asarray(ids)
    pos = {int(v): k for k, v in enumerate(ids)}
    late = shortest_visible_walks(D)
    geo = np.linalg.norm(X[:, None] - X[None], axis=2)
    H = np.asarray(hid_pos, float).reshape(-1, 3)
    dh = np.linalg.norm(X[:, None] - H[None], axis=2) if len(H) else np.zeros((len(X), 0))
    n_searched = n_hid = n_un = 0
    for (i, j), pulses in third.items():
        if int(i) not in pos or int(j) not in pos:
            continue
        a, b = pos[int(i)], pos[int(j)]
        if not (np.isfinite(r[a]) and np.isfinite(c[b])):
            continue
        n_searched += 1
        lo = 0.0 if a == b else (D[a, b] if np.isfinite(D[a, b]) else geo[a, b] - margin * W)
        hi = late[a, b]
        fam = [p["tau"] - r[a] - c[b] for p in pulses]
        hid = [e for e in fam if lo + margin * W < e < hi - margin * W]
        if not hid:
            continue
        n_hid += 1
        pred = dh[a] + dh[b] if len(H) else np.zeros(0)
        if any(not np.any(np.abs(pred - e) < margin * W) for e in hid):
            n_un += 1
    return {"n_traces_searched": n_searched, "n_traces": n_hid, "n_unexplained": n_un}


def estimate_geometry(capture, hidden: int | None = None, settings: GeometrySettings | None = None
                      ) -> GeometryEstimate:
    """Positions, normals, distances with eps, and hidden patches from ``capture``.

    Parameters
    ----------
    capture : Capture (full STIR with legs, or a relay-wall paired/confocal capture).
    hidden : number of hidden patches to look for (None: as many as the data support; 0: none).
    settings : GeometrySettings.
    """
    st = (settings or GeometrySettings()).validate()
    if capture.stir is None or not capture.legs_included:
        from .relay import estimate_relay
        return estimate_relay(capture, irf_fwhm=st.irf_fwhm)
    stats: dict = {}
    amb: list = []
    t0 = time.perf_counter()
    tmpl = on.make_template(capture, fwhm=st.irf_fwhm)
    ill, obs, O, S, snr = on.second_onsets(capture, tmpl, k_sigma=st.k_sigma, right_sigmas=st.right_sigmas)
    w = capture.grid.bin_width
    src = capture.source_xyz if capture.source_xyz is not None else np.zeros(3)
    cam = capture.camera_xyz if capture.camera_xyz is not None else src
    colocated = bool(np.linalg.norm(src - cam) < 1e-9)
    # third onsets (hidden returns) and removal of off-diagonal earliest families that are
    # hidden returns (visible patches that do not see each other)
    third = {}
    if hidden is None or hidden > 0:
        third = on.third_onsets(capture, tmpl, after=None, max_pulses=st.max_third, k_sigma=st.k_sigma)
    ii = {int(v): k for k, v in enumerate(ill)}
    oo = {int(v): k for k, v in enumerate(obs)}
    for i in ill:
        i = int(i)
        if i in oo and (i, i) in third:
            third[(i, i)] = [p for p in third[(i, i)] if p["tau"] > O[ii[i], oo[i]] + 0.5 * tmpl.width] \
                if tmpl is not None else third[(i, i)][1:]
    if third:
        for (i, j), pulses in list(third.items()):
            if i == j or not np.isfinite(O[ii[i], oo[j]]) or i not in oo or j not in ii:
                continue
            Ei = third.get((i, i), [])
            Ej = third.get((j, j), [])
            if not Ei or not Ej:
                continue
            oi_, oj_ = O[ii[i], oo[i]], O[ii[j], oo[j]]
            e = O[ii[i], oo[j]] - oi_ / 2 - oj_ / 2
            sums = [(p["tau"] - oi_) / 2 + (q["tau"] - oj_) / 2 for p in Ei for q in Ej]
            tol = 4 * max(S[ii[i], oo[j]], 1e-9) + 0.05 * (tmpl.width if tmpl else w)
            if any(abs(e - s_) < tol for s_ in sums):
                O[ii[i], oo[j]] = np.nan  # a hidden return, not a second bounce
    stats["onsets"] = StageStats("onsets", "ok", 0, time.perf_counter() - t0, True,
                                 {"n_O1": int(np.isfinite(np.diag(O[:, [oo.get(int(i), 0) for i in ill]])).sum())
                                  if len(ill) else 0,
                                  "n_O2": int(np.isfinite(O).sum()),
                                  "irf": type(tmpl).__name__ if tmpl is not None else "ideal"})
    t1 = time.perf_counter()
    sol = dm.solve_distances(ill, obs, O, S, colocated=colocated, level=st.eps_level,
                             floor=st.onset_floor_bins * w)
    stats["distances"] = StageStats("distances", "ok", 0, time.perf_counter() - t1, True,
                                    {"n_rejected": len(sol.rejected or []), "chi2": sol.residual_chi2})
    ids = sol.ids
    M = len(ids)
    t2 = time.perf_counter()
    X = em.direct_positions(capture, ids, c=sol.c)
    frame = "capture"
    if X is None or not np.isfinite(X).all():
        frame = "source-origin"
        if not np.isfinite(sol.r).all():
            raise GeometryError(f"{int(np.sum(~np.isfinite(sol.r)))} visible patches have no first "
                                "onset, so their distance to the source is unknown and they cannot "
                                "be placed. Give the capture's visible points (observed_xyz) or "
                                "check the diagonal traces.")
        # seed the embedding with the pairs whose second onsets are strong returns when the
        # onset SNRs fall into two clearly separated populations (see ``trusted_pairs``); the
        # weak ones are then kept only if they agree with that geometry
        trusted, split = trusted_pairs(ids, ill, obs, snr, np.isfinite(sol.D),
                                       min_decades=st.snr_split_decades)
        screened: list = []
        if split is not None and st.outlier_z is not None:
            Dt = np.where(trusted, sol.D, np.nan)
            np.fill_diagonal(Dt, 0.0)
            Xs, sinfo = em.embed(sol.r, sol.r_std, Dt, sol.D_std)
            dn = np.linalg.norm(Xs[:, None] - Xs[None], axis=2)
            with np.errstate(invalid="ignore"):
                zz = np.abs(dn - sol.D) / np.maximum(sol.D_std, 1e-12)
            bad = np.isfinite(sol.D) & ~trusted & (zz > st.outlier_z)
            np.fill_diagonal(bad, False)
            screened = [(int(a), int(b)) for a, b in zip(*np.nonzero(np.triu(bad, 1)))]
            _forget_pairs(sol, screened)
            stats["snr_split"] = StageStats("snr_split", "ok", 0, 0.0, True,
                                            {"threshold": split, "n_trusted": int(np.triu(trusted, 1).sum()),
                                             "n_screened": len(screened)})
            X0 = Xs
            info = {**sinfo, "n_missing": int(np.triu(~np.isfinite(sol.D), 1).sum())}
        else:
            X0, info = em.embed(sol.r, sol.r_std, sol.D, sol.D_std)
        if M < 3 or info["n_missing"] > 0 and M <= 3:
            amb.append({"kind": "underdetermined-embedding", "patches": ids.tolist(),
                        "message": f"{info['n_missing']} of the {M * (M - 1) // 2} patch-to-patch "
                                   "distances are missing (no second bounce); with so few patches the "
                                   "embedding is not unique and positions are one member of a family."})
        X = X0
        stats["embedding"] = StageStats("embedding", "ok", 0, time.perf_counter() - t2, True,
                                        {"n_missing": info["n_missing"], "rank_ratio": info["rank_ratio"],
                                         "mds_fill": info.get("fill"), "ls_chi2": info.get("chi2"),
                                         "n_starts": len(info.get("starts", []))})
        if st.refine and M >= 2:
            t3 = time.perf_counter()
            try:
                # the bounds must hold together: with n bounded terms each at eps_level, about
                # n (1 - level) of them exclude the truth (24 of 2 400 in Fig. 13), so the refinement
                # uses the Bonferroni-widened bounds that all hold at eps_level jointly
                kb = sol.joint_bound_scale() if st.joint_bounds else 1.0
                X, rinfo = em.refine_bounded(X0, sol.r, sol.r_std, sol.D, sol.D_std, kb * sol.eps, kb * sol.r_eps,
                                             outlier_z=st.outlier_z)
                stats["refine"] = StageStats("refine", str(rinfo.get("status")), int(rinfo.get("iterations", 0)),
                                             time.perf_counter() - t3, True,
                                             {"widen": rinfo.get("widen"), "n_outside": rinfo.get("n_outside", 0),
                                              "n_outliers": len(rinfo.get("outliers", [])),
                                              "bound_scale": kb})
                out_pairs = screened + list(rinfo.get("outliers", []))
                if out_pairs:
                    # a distance no point set fits (an earlier family in both O2_ij and O2_ji):
                    # reported unknown rather than kept with a bound it violates
                    _forget_pairs(sol, rinfo.get("outliers", []))
                    amb.append({"kind": "outlier-distances",
                                "patches": sorted({int(ids[k]) for p_ in out_pairs for k in p_}),
                                "pairs": [[int(ids[a]), int(ids[b])] for a, b in out_pairs],
                                "message": f"{len(out_pairs)} patch-to-patch distances disagree with every "
                                           f"embedding (residual > {st.outlier_z:g} std): their second "
                                           "onsets are most likely an earlier family (a return via a "
                                           "hidden patch, or via a third patch between two that do not "
                                           "see each other). They were dropped and the positions "
                                           "re-solved."})
                if rinfo.get("widen", 1.0) > 1.0:
                    amb.append({"kind": "eps-inconsistent", "patches": [],
                                "message": f"the eps bounds were mutually infeasible; positions were "
                                           f"found inside bounds widened x{rinfo['widen']:g}."})
            except SolverError as exc:
                stats["refine"] = StageStats("refine", f"failed: {exc.status}", 0,
                                             time.perf_counter() - t3, False)
                raise
    vis_mask = np.ones(M, bool)
    t4 = time.perf_counter()
    labels = nm.plane_groups(X) if M >= 6 else np.full(M, -1)
    normals = nm.estimate_normals(X, visible=vis_mask, camera=cam if frame == "capture" else np.zeros(3),
                                  labels=labels) if M >= 3 else np.full((M, 3), np.nan)
    stats["normals"] = StageStats("normals", "ok", 0, time.perf_counter() - t4, True,
                                  {"n_planes": int(len(np.unique(labels[labels >= 0])))})
    # hidden patches
    hid_pos = np.zeros((0, 3))
    hid_std = np.zeros((0, 3))
    hdb = []
    if third:
        t5 = time.perf_counter()
        rd = {int(i): float(sol.r[k]) for k, i in enumerate(ids)}
        cd = {int(i): float(sol.c[k]) for k, i in enumerate(ids)}
        exc_on = hm.excess_onsets(third, ids, rd, cd)
        if exc_on:
            z = dm.eps_quantile(st.eps_level)
            W = tmpl.width if tmpl is not None else w
            if st.hidden_method == "paper":
                n_h = hidden if hidden is not None else max(len(v[0]) for (a, b), v in exc_on.items() if a == b)
                res = hm.label_paper(exc_on, X, ids, n_h, level_z=z, floor=st.onset_floor_bins * w,
                                     camera=cam if frame == "capture" else np.zeros(3))
            else:
                res = hm.label_robust(exc_on, X, ids, n_hidden=hidden, tol_floor=0.5 * W, level_z=z,
                                      floor=st.onset_floor_bins * w,
                                      camera=cam if frame == "capture" else np.zeros(3))
            hid_pos, hid_std = res["positions"], res["position_std"]
            amb.extend(res["ambiguities"])
            base = int(max(ids.max(), capture.ill_ids().max(), capture.obs_ids().max())) + 1
            for k in range(len(hid_pos)):
                hdb.append({"id": base + k, "visible_ids": ids.tolist(), "distances": res["h"][k],
                            "eps": res["h_eps"][k]})
            stats["hidden"] = StageStats("hidden", "ok", 0, time.perf_counter() - t5, True,
                                         {"method": res["method"], "n_hidden": int(len(hid_pos)),
                                          "edm_rank_score": res.get("edm_rank_score")})
    if third and M >= 3:
        W = tmpl.width if tmpl is not None else w
        un = unexplained_hidden_returns(third, ids, X, sol.D, sol.r, sol.c, hid_pos, W)
        stats.setdefault("hidden", StageStats("hidden", "ok", 0, 0.0, True, {}))
        stats["hidden"].extra["n_traces_hidden_only_returns"] = un["n_traces"]
        stats["hidden"].extra["n_traces_unexplained"] = un["n_unexplained"]
        if un["n_unexplained"] >= max(10, int(0.01 * un["n_traces_searched"])):
            amb.append({"kind": "unexplained-hidden-returns", "patches": [],
                        "n_traces": un["n_unexplained"],
                        "message": f"{un['n_unexplained']} of {un['n_traces_searched']} traces hold a return that "
                                   "only a hidden surface can produce (after their first/second bounce, "
                                   "before any visible path of three or more bounces), and the "
                                   f"{len(hid_pos)} hidden patches placed do not explain it. An extended "
                                   "hidden surface blends the returns of its parts within one IRF width, "
                                   "so they cannot be labeled patch by patch; its patches are not placed."})
    K = len(hid_pos)
    base = int(max(ids.max(), capture.ill_ids().max(), capture.obs_ids().max())) + 1
    all_ids = np.concatenate([ids, base + np.arange(K)])
    P = np.vstack([X, hid_pos]) if K else X
    Dfull = np.full((M + K, M + K), np.nan)
    Efull = np.full((M + K, M + K), np.inf)
    Dfull[:M, :M], Efull[:M, :M] = sol.D, sol.eps
    for k, b in enumerate(hdb):
        Dfull[M + k, :M] = Dfull[:M, M + k] = b["distances"]
        Efull[M + k, :M] = Efull[:M, M + k] = b["eps"]
        Dfull[M + k, M + k], Efull[M + k, M + k] = 0.0, 0.0
    # onsets carry no orientation: a hidden patch's normal is left to the joint (reflectance) NLP,
    # which estimates it from third-bounce amplitudes where the data identify it
    hn = np.full((K, 3), np.nan)
    if K:
        amb.append({"kind": "hidden-normals-unmeasured", "patches": (base + np.arange(K)).tolist(),
                    "message": "onset times do not measure the orientation of hidden patches; their "
                               "normals are left to the joint NLP (stircasadi.estimate)."})
    calib = capture.extras.get("observed_normals") if isinstance(capture.extras, dict) else None
    if calib is not None and frame == "capture":
        calib = np.asarray(calib, float)
        obs_known = capture.obs_ids()
        if calib.shape == (len(obs_known), 3) and np.all(np.isfinite(calib)):
            for k, i in enumerate(ids):
                hit = np.flatnonzero(obs_known == i)
                if hit.size:
                    normals[k] = calib[hit[0]] / np.linalg.norm(calib[hit[0]])
            stats["normals"].extra["source"] = "calibrated camera (observed_normals)"
    est = GeometryEstimate(
        ids=all_ids, positions=P, visible=np.concatenate([vis_mask, np.zeros(K, bool)]),
        normals=np.vstack([normals, hn]) if K else normals, distances=Dfull, eps=Efull,
        position_std=np.vstack([np.full((M, 3), np.nan), hid_std]) if K else None,
        hidden_distance_bounds=hdb, source_xyz=src if frame == "capture" else np.zeros(3),
        camera_xyz=cam if frame == "capture" else np.zeros(3), frame=frame,
        plane_labels=np.concatenate([labels, -np.ones(K, int)]),
        onsets={"ill_ids": ill, "obs_ids": obs, "O": O, "O_std": S, "snr": snr,
                "r": sol.r, "r_std": sol.r_std, "third": third},
        stats=stats, ambiguities=amb, eps_level=st.eps_level)
    return est
