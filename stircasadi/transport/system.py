"""The transient rendering equation of a scene as a delay network (built once, solved three ways).

Equation implemented
--------------------
Unknowns ("nodes") are outgoing radiances: one node ``B_k`` per Lambertian patch (its radiance is
the same in every direction) and, for every glossy (Phong) patch g, one node ``L_e`` per leg e
leaving g (its radiance depends on the direction). With delays in metres of path,

    u_r(t) = sum_p S_rp u_p^src(t - s_rp) + sum_c T_rc u_c(t - l_rc)                      (1)
    y_jp(t) = sum_c O_jc u_c(t - o_jc)           with u^src_p = phi delta(t) aimed at p    (2)

where, for a leg e from h to k of length l_e and small-patch form factor G_e (see
``stircasadi.radiometry``; a mirror leg is the image-source path through a mirror patch):

* source terms ``S``: the pulse at p gives irradiance ``phi / a_p`` after ``|s - z_p|``; the
  node of p receives ``f_p(w_src, w_out) phi / a_p``;
* transfer terms ``T``: node c (leaving h along e) feeds node r (leaving k) with
  ``f_k(w_in = back along e, w_out) G_e`` after ``l_e``;
* observation terms ``O``: the camera reads the node carrying the radiance leaving j toward it
  (the Lambertian node of j, or the "camera link" node of a glossy j), after ``|z_j - o|``.

A walk source -> n nodes -> camera is an n-bounce light path (n = 1: the first bounce).

What it neglects: see ``stircasadi.radiometry`` (small patches) and ``stircasadi.brdf``
(mirrors); light reflected twice in a row by mirrors (mirror -> mirror) is not modelled, and a
mirror patch seen directly by the camera appears black.

``delay_mode="integer"`` rounds every leg to a whole number of bins (at least one), as the
paper's state-space model does; ``"exact"`` keeps the true lengths.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..brdf import Mirror, Phong
from ..errors import TransportError
from ..radiometry import direct_leg, mirror_leg, rows, source_irradiance, vec
from ..scene import Scene


@dataclass
class Legs:
    """Patch-to-patch legs (including image-source legs through mirror patches)."""

    src: np.ndarray      # (E,) emitting patch
    dst: np.ndarray      # (E,) receiving patch
    length: np.ndarray   # (E,) metres of path
    g: np.ndarray        # (E,) form factor (times mirror reflectance for mirror legs)
    dir_out: np.ndarray  # (E, 3) unit direction leaving src
    dir_in: np.ndarray   # (E, 3) unit direction at dst pointing back toward the light
    via: np.ndarray      # (E,) mirror patch index, -1 for a direct leg


@dataclass
class TransportSystem:
    """Nodes and delay terms of equations (1)-(2). Build with ``TransportSystem.build(scene)``."""

    n_nodes: int
    node_patch: np.ndarray   # (N,) patch whose outgoing radiance the node is
    node_leg: np.ndarray     # (N,) leg index for glossy link nodes, -1 for Lambertian nodes
    ill_ids: np.ndarray      # illuminated patch ids (STIR rows)
    obs_ids: np.ndarray      # observed patch ids (STIR columns)
    # terms: (row, col, coef, length)
    S: tuple                 # rows = node, cols = illuminated row index
    T: tuple                 # rows = node, cols = node
    O: tuple                 # rows = observed column index, cols = node
    bin_width: float | None = None
    delay_mode: str = "exact"
    metadata: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ build
    @classmethod
    def build(cls, scene: Scene, delay_mode: str = "exact", bin_width: float | None = None,
              legs_included: bool = True, link_level: bool = False) -> "TransportSystem":
        """Build the network. ``link_level=True`` gives every patch per-leg nodes (the paper's
        general form-factor model f_kij, a state per link); the STIR is the same."""
        if delay_mode not in ("exact", "integer"):
            raise TransportError(f"delay_mode must be 'exact' or 'integer'; got {delay_mode!r}.")
        if delay_mode == "integer" and not (bin_width and bin_width > 0):
            raise TransportError("delay_mode='integer' needs the grid's bin_width to round legs.")
        legs = scene_legs(scene)
        z, n = scene.positions, scene.normals
        brdfs = scene.brdfs
        M = scene.n_patches
        mirror = np.array([isinstance(b, Mirror) for b in brdfs])
        glossy = np.array([isinstance(b, Phong) and b.specular > 0 for b in brdfs])
        if link_level:
            glossy = ~mirror
        ill = scene.illuminated_ids
        obs = scene.observed_ids
        ill_row = -np.ones(M, int)
        ill_row[ill] = np.arange(len(ill))
        obs_col = -np.ones(M, int)
        obs_col[obs] = np.arange(len(obs))
        d_src = scene.source_distances
        d_cam = scene.camera_distances
        w_src = (scene.source - z) / d_src[:, None]
        w_cam = (scene.camera - z) / d_cam[:, None]
        if not legs_included:
            d_src = np.zeros_like(d_src)
            d_cam = np.zeros_like(d_cam)

        # ---- nodes: one per Lambertian (or diffuse-only Phong) patch; for a glossy patch one per leg
        # out of it, plus one "camera link" node when the camera sees it. A walk through n nodes is an
        # n-bounce path, for every node kind.
        node_of_patch = -np.ones(M, int)
        node_patch, node_leg = [], []
        for k in range(M):
            if not glossy[k] and not mirror[k]:
                node_of_patch[k] = len(node_patch)
                node_patch.append(k)
                node_leg.append(-1)
        leg_node = -np.ones(len(legs.src), int)
        for e in np.flatnonzero(glossy[legs.src]):
            leg_node[e] = len(node_patch)
            node_patch.append(int(legs.src[e]))
            node_leg.append(int(e))
        cam_node = -np.ones(M, int)
        for k in np.flatnonzero(glossy & (obs_col >= 0)):
            cam_node[k] = len(node_patch)
            node_patch.append(int(k))
            node_leg.append(-2)
        node_patch = np.array(node_patch, int)
        node_leg = np.array(node_leg, int)

        def f_at(k, w_in, w_out):
            """BRDF of patch k (scalar index) for arrays of directions (...,3)."""
            nk = n[k]
            ci = w_in @ nk
            co = w_out @ nk
            cio = np.sum(w_in * w_out, axis=-1)
            return np.broadcast_to(brdfs[k].value(ci, co, cio), np.shape(ci))

        # ---- source terms S: the pulse at p feeds p's node(s)
        S_r, S_c, S_v, S_l = [], [], [], []
        for p in ill:
            e_irr = source_irradiance(scene.phi, scene.areas[p])
            if node_of_patch[p] >= 0:
                S_r.append([node_of_patch[p]]); S_c.append([ill_row[p]])
                S_v.append(f_at(p, w_src[p], n[p]) * e_irr); S_l.append([d_src[p]])
            elif glossy[p]:
                es = np.flatnonzero(legs.src == p)
                outs = [legs.dir_out[es]]
                nodes = [leg_node[es]]
                if cam_node[p] >= 0:
                    outs.append(w_cam[p][None]); nodes.append([cam_node[p]])
                w_out = np.concatenate(outs)
                vals = f_at(p, np.repeat(w_src[p][None], len(w_out), 0), w_out) * e_irr
                S_r.append(np.concatenate(nodes)); S_c.append(np.full(len(w_out), ill_row[p]))
                S_v.append(vals); S_l.append(np.full(len(w_out), d_src[p]))

        # ---- transfer terms T: the node carrying light along leg e (h -> k) feeds k's node(s)
        carrier = np.where(glossy[legs.src], leg_node, node_of_patch[legs.src])
        ok = carrier >= 0
        rho = np.array([b.diffuse_albedo for b in brdfs])
        T_r, T_c, T_v, T_l = [], [], [], []
        e_idx = np.flatnonzero(ok & (node_of_patch[legs.dst] >= 0))  # Lambertian receivers
        T_r.append(node_of_patch[legs.dst[e_idx]]); T_c.append(carrier[e_idx])
        T_v.append(rho[legs.dst[e_idx]] / np.pi * legs.g[e_idx]); T_l.append(legs.length[e_idx])
        for k in np.flatnonzero(glossy):  # glossy receivers: one term per (leg in, leg out)
            e_in = np.flatnonzero(ok & (legs.dst == k))
            if not len(e_in):
                continue
            e_out = np.flatnonzero(legs.src == k)
            outs, nodes = [legs.dir_out[e_out]], [leg_node[e_out]]
            if cam_node[k] >= 0:
                outs.append(w_cam[k][None]); nodes.append([cam_node[k]])
            w_out = np.concatenate(outs)
            nodes = np.concatenate(nodes)
            ein, iout = np.meshgrid(e_in, np.arange(len(w_out)), indexing="ij")
            fv = f_at(k, legs.dir_in[ein], w_out[iout])
            T_r.append(nodes[iout].ravel()); T_c.append(carrier[ein].ravel())
            T_v.append((fv * legs.g[ein]).ravel()); T_l.append(legs.length[ein].ravel())

        # ---- observation terms O: the camera reads the node leaving j toward it
        O_r, O_c, O_v, O_l = [], [], [], []
        for k in obs:
            node = node_of_patch[k] if node_of_patch[k] >= 0 else cam_node[k]
            if node >= 0:  # mirrors seen directly stay black
                O_r.append([obs_col[k]]); O_c.append([node]); O_v.append([1.0]); O_l.append([d_cam[k]])

        def pack(r, c, v, l):
            cat = (lambda xs, dt: np.concatenate([np.atleast_1d(np.asarray(x, dt)) for x in xs])
                   if len(xs) else np.zeros(0, dt))
            r, c, v, l = cat(r, int), cat(c, int), cat(v, float), cat(l, float)
            keep = v != 0.0
            return r[keep], c[keep], v[keep], l[keep]

        S, T, O = pack(S_r, S_c, S_v, S_l), pack(T_r, T_c, T_v, T_l), pack(O_r, O_c, O_v, O_l)
        meta = {
            "n_nodes": int(len(node_patch)),
            "glossy_patches": np.flatnonzero(glossy).tolist(),
            "mirror_patches": np.flatnonzero(mirror).tolist(),
            "glossy_terms": bool(glossy.any()),
            "mirror_legs": int(np.sum(legs.via >= 0)),
            "occlusion": "ray-cast (trimesh)" if scene.needs_occlusion else "none (no occluders)",
            "legs_included": bool(legs_included),
            "link_level": bool(link_level),
        }
        sys_ = cls(n_nodes=len(node_patch), node_patch=node_patch, node_leg=node_leg,
                   ill_ids=ill, obs_ids=obs, S=S, T=T, O=O, metadata=meta)
        if delay_mode == "integer":
            sys_ = sys_.rounded(bin_width)
        return sys_

    # ------------------------------------------------------------------ variants
    def rounded(self, bin_width: float) -> "TransportSystem":
        """The same network with every leg rounded to whole bins (at least one bin), in metres.

        Each leg is rounded on its own, as in the paper's shift-register state space, so a path's
        delay is the sum of its rounded legs.
        """
        def r(t):
            rr, cc, vv, ll = t
            return rr, cc, vv, np.maximum(np.rint(ll / bin_width), 1.0) * bin_width
        return TransportSystem(self.n_nodes, self.node_patch, self.node_leg, self.ill_ids,
                               self.obs_ids, r(self.S), r(self.T), r(self.O), bin_width,
                               "integer", dict(self.metadata))

    @property
    def n_ill(self) -> int:
        return len(self.ill_ids)

    @property
    def n_obs(self) -> int:
        return len(self.obs_ids)

    def arrival_window(self, bounces: int | None) -> tuple[float, float]:
        """Earliest and latest arrival (metres) of paths with 1..bounces bounces (None: latest = inf)."""
        S_l, T_l, O_l = self.S[3], self.T[3], self.O[3]
        if not (len(S_l) and len(O_l)):
            return (np.inf, -np.inf)
        lo = float(S_l.min() + O_l.min())
        if bounces is None:
            return lo, np.inf
        t_hi = float(T_l.max()) if len(T_l) else 0.0
        return lo, float(S_l.max() + O_l.max() + (bounces - 1) * t_hi)

    def steady_matrices(self):
        """Real sparse matrices of (1)-(2) at zero frequency: S0 (N, n_ill), T0 (N, N), O0 (n_obs, N)."""
        from scipy import sparse

        def sp(t, shape):
            r, c, v, _ = t
            return sparse.coo_matrix((v, (r, c)), shape=shape).tocsr()
        N = self.n_nodes
        return sp(self.S, (N, self.n_ill)), sp(self.T, (N, N)), sp(self.O, (self.n_obs, N))


def scene_legs(scene: Scene) -> Legs:
    """All legs between patches: direct (facing, unoccluded) and image-source legs via mirrors.

    Lengths, form factors and directions come from ``radiometry.direct_leg`` /
    ``radiometry.mirror_leg`` (the formulas the symbolic model evaluates too); whether a mirror
    leg exists is ``Mirror.transfer``'s hit test."""
    z, n, a = scene.positions, scene.normals, scene.areas
    mirror = np.array([isinstance(b, Mirror) for b in scene.brdfs])
    vis = scene.patch_visibility.copy()
    # legs into or out of mirror patches are replaced by image-source legs through them
    vis[mirror, :] = False
    vis[:, mirror] = False
    h, k = np.nonzero(vis)
    leg = direct_leg(vec(z[h]), vec(z[k]), vec(n[h]), vec(n[k]), a[h])
    src, dst, length, gg, dout, din, via = ([h], [k], [leg.length], [leg.g], [rows(leg.dir_out)],
                                            [rows(leg.dir_in)], [-np.ones(len(h), int)])
    if mirror.any():
        others = np.flatnonzero(~mirror)
        for m in np.flatnonzero(mirror):
            R = scene.brdfs[m].reflectance
            hh, kk = np.meshgrid(others, others, indexing="ij")
            hh, kk = hh.ravel(), kk.ravel()
            sel = hh != kk
            hh, kk = hh[sel], kk[sel]
            hit, _, _, hp = Mirror.transfer(z[hh], z[m], n[m], a[m], z[kk], R)
            if not hit.any():
                continue
            hh, kk, hp = hh[hit], kk[hit], hp[hit]
            ml = mirror_leg(vec(z[hh]), vec(z[kk]), vec(n[hh]), vec(n[kk]), a[hh],
                            vec(np.broadcast_to(z[m], (len(hh), 3))),
                            vec(np.broadcast_to(n[m], (len(hh), 3))), R)
            keep = (np.asarray(ml.g) > 0)
            if scene.needs_occlusion and keep.any():
                idx = np.flatnonzero(keep)
                clear = scene.segments_clear(z[hh[idx]], hp[idx]) & scene.segments_clear(hp[idx], z[kk[idx]])
                keep[idx[~clear]] = False
            src.append(hh[keep]); dst.append(kk[keep]); length.append(np.asarray(ml.length)[keep])
            gg.append(np.asarray(ml.g)[keep]); dout.append(rows(ml.dir_out)[keep])
            din.append(rows(ml.dir_in)[keep]); via.append(np.full(int(keep.sum()), m))
    return Legs(*(np.concatenate(x) for x in (src, dst, length, gg, dout, din, via)))
