"""Reflectance-based segmentation: patches grouped into materials by their estimated BRDF.

When to use
-----------
To say which patches are made of the same material, and which cannot be told apart or assigned,
from the estimate alone (``SceneBelief``): its BRDF parameters and their covariance. Patches
that the data cannot distinguish share a material; the number of materials is chosen by the data.

Model and equations
-------------------
Each patch p reports features ``x_p`` (albedo; and specular, exponent for Phong patches) with
covariance ``C_p`` (its block of the estimate's covariance). A material c is one true feature
vector ``mu_c``; a patch of material c has ``x_p ~ N(mu_c, C_p)``. For a group of patches

    mu = (sum C_p^-1)^-1 sum C_p^-1 x_p,      chi2 = sum (x_p - mu)^T C_p^-1 (x_p - mu)

(the weighted mean and its misfit; chi2 ~ chi-square with d (n - 1) degrees of freedom when the
group is one material). Candidate partitions come from agglomerative merging (join the two groups
whose union raises chi2 least: by ``(mu_A - mu_B)^T (S_A + S_B)^-1 (mu_A - mu_B)``, Ward's
criterion with known covariances), each polished by reassigning patches to the nearest mean
(Mahalanobis). The number of materials K is the data's: the smallest K at which every material
passes the chi-square homogeneity test at level ``alpha`` (statistically indistinguishable
patches share a material; a split is made only where the data reject a merge). BIC(K) =
chi2_total(K) + K d ln(n d) is reported beside it for comparison: on optimised partitions its
penalty is too weak (splitting one material's patches at their largest gap lowers chi2 by more
than d ln(n d) too often), so it does not choose K.

Reported at the level ``alpha`` (default 0.01):

* a material whose chi2 exceeds its chi-square quantile (``homogeneous: False``; only with
  ``max_materials`` capping K): its patches are not all one material at this noise;
* ambiguous patches: consistent (p > alpha) with another material's mean too, given its own
  covariance plus the uncertainty of that mean; listed with every candidate and its p-value;
* outliers: inconsistent (p < alpha) with their own material (leave-one-out mean);
* unsegmented patches: no BRDF estimate or no covariance for it (say why).

Patches of different BRDF kinds (Lambertian, Phong) are segmented separately (different
features). Neglects: covariance between patches (the estimate's cross terms), a true spread of
a material's parameters (texture): such a spread shows up as extra materials or as
heterogeneous ones.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2 as chi2_dist

from ..errors import EstimateInputError
from .belief import SceneBelief

__all__ = ["SegmentSettings", "Segmentation", "segment", "segment_features"]

_FEATURES = {"lambertian": ("albedo",), "phong": ("albedo", "specular", "exponent")}


@dataclass
class SegmentSettings:
    """Settings of ``segment``."""

    #: test level alpha of the homogeneity, membership and ambiguity tests
    level: float = 0.01
    #: most materials considered by BIC (None: every patch its own material at most)
    max_materials: int | None = None
    #: reassignment sweeps that polish each candidate partition
    refine_sweeps: int = 10

    def validate(self) -> "SegmentSettings":
        if not (0.0 < self.level < 0.5):
            raise EstimateInputError(f"level must be in (0, 0.5); got {self.level!r}.")
        if self.max_materials is not None and not (isinstance(self.max_materials, int) and self.max_materials >= 1):
            raise EstimateInputError(f"max_materials must be an integer >= 1 or None; got {self.max_materials!r}.")
        if not (isinstance(self.refine_sweeps, int) and self.refine_sweeps >= 0):
            raise EstimateInputError(f"refine_sweeps must be an integer >= 0; got {self.refine_sweeps!r}.")
        return self


@dataclass
class Segmentation:
    """Materials, their patches, and what the data cannot decide (ids are estimate ids)."""

    ids: np.ndarray                       # segmented patch ids
    labels: np.ndarray                    # material index per segmented patch
    materials: list                       # per material: ids, kind, features, mean, std, chi2, dof, p, homogeneous
    ambiguous: list = field(default_factory=list)     # {"id", "material", "candidates": {m: p}}
    outliers: list = field(default_factory=list)      # {"id", "material", "p"}
    unsegmented: list = field(default_factory=list)   # {"id", "reason"}
    bic: dict = field(default_factory=dict)           # kind -> {K: BIC}
    level: float = 0.01

    @property
    def n_materials(self) -> int:
        return len(self.materials)

    def material_of(self, patch_id: int) -> int:
        hit = np.flatnonzero(self.ids == int(patch_id))
        if not hit.size:
            raise EstimateInputError(f"Patch {patch_id} was not segmented (see unsegmented).")
        return int(self.labels[hit[0]])

    def to_json_dict(self) -> dict:
        return {"format": "stircasadi.segmentation", "version": 1, "level": self.level,
                "ids": self.ids.tolist(), "labels": self.labels.tolist(),
                "materials": self.materials, "ambiguous": self.ambiguous, "outliers": self.outliers,
                "unsegmented": self.unsegmented,
                "bic": {k: {str(kk): vv for kk, vv in v.items()} for k, v in self.bic.items()}}


def segment(belief: SceneBelief, settings: SegmentSettings | None = None) -> Segmentation:
    """Segment the estimate's patches into materials (module doc)."""
    settings = (settings or SegmentSettings()).validate()
    groups: dict = {}
    unseg = []
    for k, pid in enumerate(belief.ids):
        pid = int(pid)
        if pid in belief.proxy_ids:
            unseg.append({"id": pid, "reason": "known only through albedo x area: no albedo to compare"})
            continue
        kind = belief.kinds[k]
        idx = np.concatenate([belief.slot(f, pid) for f in _FEATURES[kind]])
        C = belief.covariance[np.ix_(idx, idx)]
        if np.any(np.diag(C) <= 0):
            missing = [belief.names[i] for i in idx if belief.covariance[i, i] <= 0]
            unseg.append({"id": pid, "reason": f"no uncertainty reported for {missing}: cannot test "
                                               "whether it differs from other patches"})
            continue
        groups.setdefault(kind, []).append((pid, belief.values[idx], C))
    ids, labels, mats, amb, outl, bic = [], [], [], [], [], {}
    for kind, items in groups.items():
        seg = segment_features(np.array([x for _, x, _ in items]), np.array([c for _, _, c in items]),
                               settings)
        off = len(mats)
        pids = np.array([p for p, _, _ in items])
        for m in seg["materials"]:
            m["ids"] = pids[m.pop("members")].tolist()
            m["kind"], m["features"] = kind, list(_FEATURES[kind])
            m["index"] = off + m["index"]
            mats.append(m)
        for a in seg["ambiguous"]:
            amb.append({"id": int(pids[a["member"]]), "material": off + a["material"],
                        "candidates": {off + c: p for c, p in a["candidates"].items()}})
        for o in seg["outliers"]:
            outl.append({"id": int(pids[o["member"]]), "material": off + o["material"], "p": o["p"]})
        ids.extend(pids.tolist())
        labels.extend((off + seg["labels"]).tolist())
        bic[kind] = seg["bic"]
    return Segmentation(ids=np.array(ids, int), labels=np.array(labels, int), materials=mats,
                        ambiguous=amb, outliers=outl, unsegmented=unseg, bic=bic, level=settings.level)


# ---------------------------------------------------------------------- the statistics
def _group(x, Winv, members):
    """Weighted mean, its covariance and chi2 of a group (Winv: per-patch inverse covariances)."""
    P = Winv[members].sum(axis=0)
    cov = np.linalg.inv(P)
    mu = cov @ np.einsum("pij,pj->i", Winv[members], x[members])
    r = x[members] - mu
    return mu, cov, float(np.einsum("pi,pij,pj->", r, Winv[members], r))


def _partition_chi2(x, Winv, labels):
    return sum(_group(x, Winv, np.flatnonzero(labels == c))[2] for c in np.unique(labels))


def _refine(x, Winv, labels, sweeps):
    """Reassign each patch to the group mean nearest in Mahalanobis distance, while chi2 drops."""
    best = _partition_chi2(x, Winv, labels)
    for _ in range(sweeps):
        cs = np.unique(labels)
        mus = np.array([_group(x, Winv, np.flatnonzero(labels == c))[0] for c in cs])
        r = x[:, None, :] - mus[None, :, :]
        d2 = np.einsum("pci,pij,pcj->pc", r, Winv, r)
        new = cs[np.argmin(d2, axis=1)]
        if np.array_equal(new, labels) or len(np.unique(new)) < len(cs):
            break
        c2 = _partition_chi2(x, Winv, new)
        if c2 >= best - 1e-12:
            break
        labels, best = new, c2
    return labels, best


def segment_features(x: np.ndarray, C: np.ndarray, settings: SegmentSettings | None = None) -> dict:
    """Segment feature vectors ``x`` (n, d) with covariances ``C`` (n, d, d) (module doc).

    Returns a dict with ``labels``, ``materials`` (members, mean, std, chi2, dof, p,
    homogeneous), ``ambiguous``, ``outliers`` and ``bic`` ({K: BIC}).
    """
    settings = (settings or SegmentSettings()).validate()
    x = np.atleast_2d(np.asarray(x, float))
    n, d = x.shape
    C = np.asarray(C, float).reshape(n, d, d)
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(C))):
        raise EstimateInputError("Segmentation features and covariances must be finite.")
    Winv = np.linalg.inv(C)
    alpha = settings.level
    # agglomerative merging: a partition for every K from n down to 1. Joining groups A and B
    # raises chi2 by (mu_A - mu_B)^T (S_A + S_B)^-1 (mu_A - mu_B) (S: covariance of a mean)
    mus = [x[p] for p in range(n)]
    covs = [C[p] for p in range(n)]
    clusters = [[p] for p in range(n)]
    partitions = {n: np.arange(n)}
    while len(clusters) > 1:
        M, S = np.array(mus), np.array(covs)
        r = M[:, None, :] - M[None, :, :]
        dc = np.einsum("abi,abi->ab", r, np.linalg.solve(S[:, None] + S[None, :], r[..., None])[..., 0])
        dc[np.tril_indices(len(clusters))] = np.inf
        a, b = np.unravel_index(np.argmin(dc), dc.shape)
        clusters[a] = clusters[a] + clusters[b]
        mus[a], covs[a], _ = _group(x, Winv, np.array(clusters[a]))
        del clusters[b], mus[b], covs[b]
        lab = np.empty(n, int)
        for k, c in enumerate(clusters):
            lab[c] = k
        partitions[len(clusters)] = lab
    kmax = n if settings.max_materials is None else min(n, settings.max_materials)
    N = n * d
    bic, labels = {}, None
    for K in range(1, kmax + 1):
        lab, c2 = _refine(x, Winv, partitions[K], settings.refine_sweeps)
        bic[K] = float(c2 + K * d * math.log(max(N, 2)))
        if labels is None and all(_homogeneous_p(x, Winv, np.flatnonzero(lab == c), d) >= alpha
                                  for c in np.unique(lab)):
            labels = lab
    if labels is None:  # cannot happen for kmax = n (singletons are homogeneous); max_materials
        labels = _refine(x, Winv, partitions[kmax], settings.refine_sweeps)[0]
    labels = _relabel(labels, x)
    mats, groups = [], []
    for c in range(labels.max() + 1):
        mem = np.flatnonzero(labels == c)
        mu, cov, c2 = _group(x, Winv, mem)
        dof = d * (len(mem) - 1)
        p = float(chi2_dist.sf(c2, dof)) if dof > 0 else 1.0
        groups.append((mem, mu, cov))
        mats.append({"index": c, "members": mem, "mean": mu.tolist(),
                     "std": np.sqrt(np.diag(cov)).tolist(), "chi2": c2, "dof": dof, "p": p,
                     "homogeneous": bool(p >= alpha)})
    amb, outl = [], []
    for p in range(n):
        own = labels[p]
        cands = {}
        for c, (mem, mu, cov) in enumerate(groups):
            if c == own:
                rest = mem[mem != p]
                if not len(rest):
                    continue
                mu_o, cov_o, _ = _group(x, Winv, rest)
                pv = _membership_p(x[p], C[p], mu_o, cov_o)
                if pv < alpha:
                    outl.append({"member": p, "material": int(own), "p": pv})
            else:
                pv = _membership_p(x[p], C[p], mu, cov)
                if pv >= alpha:
                    cands[c] = pv
        if cands:
            amb.append({"member": p, "material": int(own), "candidates": cands})
    return {"labels": labels, "materials": mats, "ambiguous": amb, "outliers": outl, "bic": bic}


def _homogeneous_p(x, Winv, mem, d) -> float:
    dof = d * (len(mem) - 1)
    return float(chi2_dist.sf(_group(x, Winv, mem)[2], dof)) if dof > 0 else 1.0


def _membership_p(x, C, mu, cov) -> float:
    r = x - mu
    d2 = float(r @ np.linalg.solve(C + cov, r))
    return float(chi2_dist.sf(d2, len(x)))


def _relabel(labels, x):
    """Number materials by increasing first feature (albedo), for stable reports."""
    cs = np.unique(labels)
    order = sorted(cs, key=lambda c: float(np.mean(x[labels == c, 0])))
    remap = {c: k for k, c in enumerate(order)}
    return np.array([remap[c] for c in labels], int)
