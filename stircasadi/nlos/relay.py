"""The relay description every NLOS reconstruction reads: traces with their visible end points.

When to use: build a :class:`Relay` from a paired/confocal relay-wall ``Capture``
(:func:`from_capture`) or by hand from a full STIR with legs (Fig. 13: the relay is the visible
patches; :func:`from_stir`). Every algorithm in ``stircasadi.nlos`` reads this one structure:

    trace p:  laser spot L_p (normal nL_p) -> hidden point X -> detection spot D_p (normal nD_p)
    arrival:  t = leg_p + |L_p - X| + |X - D_p|       (metres of optical path)

``leg_p`` is 0 for rectified captures (``legs_included=False``) and |s - L_p| + |D_p - o| for a
full STIR with legs. ``gain_p`` multiplies the third-bounce amplitude of trace p (the product of
the relay BRDFs f(L_p) f(D_p) where they are known, else 1 and a global gain is fitted).

The relay frame (``centre``, in-plane axes ``u``, ``v`` and normal ``w`` pointing into the
hidden scene) is the best plane through the relay points (SVD); volumes and surfaces are
gridded parallel to it. Neglects: nothing here; it only describes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ReconstructionError
from ..timegrid import TimeGrid

__all__ = ["Relay", "from_capture", "from_stir", "ConfocalGrid", "confocal_grid", "plane_frame"]


def plane_frame(points: np.ndarray, towards: np.ndarray | None = None):
    """(centre, u, v, w) of the best plane through ``points``; ``w`` points to ``towards`` when
    given (else to +z), ``u`` is the in-plane direction closest to +x."""
    P = np.asarray(points, float)
    c = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    w = vt[-1]
    ref = (np.asarray(towards, float) - c) if towards is not None else np.array([0.0, 0.0, 1.0])
    if w @ ref < 0:
        w = -w
    ex = np.array([1.0, 0.0, 0.0]) if abs(w[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = ex - (ex @ w) * w
    u /= np.linalg.norm(u)
    v = np.cross(w, u)
    return c, u, v, w


@dataclass
class Relay:
    """Traces and the visible geometry of their light paths (see the module docstring).

    Attributes
    ----------
    traces : (P, T) measurements on ``grid`` (time last).
    grid : the time axis (metres of optical path).
    L, D : (P, 3) laser and detection points on the relay surface.
    nL, nD : (P, 3) unit normals of the relay surface at L and D (facing the hidden scene).
    leg : (P,) time offset added to every path of the trace (0 when rectified).
    gain : (P,) amplitude factor of the trace's relay (f(L) f(D)); 1 when unknown.
    sigma : noise std per bin, broadcastable to ``traces``; None = Poisson (counts).
    irf : the sensor's impulse response object when the capture states one (else None: fitted).
    confocal : whether L == D for every trace.
    frame : (centre, u, v, w) of the relay plane, w into the hidden scene.
    footprint : (P, 2) variance (m^2) of the trace's relay spots along the frame's ``u`` and
        ``v`` when one trace sums the returns of several scan points (laser and detection spot
        moving together; ``nlos.estimate.subsample_confocal``: s^2 (k^2 - 1) / 12 for k x k
        points of spacing s); None: zeros (one scan point per trace).
    """

    traces: np.ndarray
    grid: TimeGrid
    L: np.ndarray
    D: np.ndarray
    nL: np.ndarray
    nD: np.ndarray
    leg: np.ndarray
    gain: np.ndarray
    sigma: np.ndarray | float | None = None
    irf: object = None
    confocal: bool = False
    frame: tuple = field(default=None)
    meta: dict = field(default_factory=dict)
    footprint: np.ndarray | None = None

    def __post_init__(self):
        self.validate()

    def validate(self) -> "Relay":
        tr = np.asarray(self.traces, float)
        if tr.ndim != 2 or tr.shape[1] != self.grid.n_bins:
            raise ReconstructionError(f"Relay traces must be (P, n_bins={self.grid.n_bins}); got {tr.shape}.")
        if not np.all(np.isfinite(tr)):
            raise ReconstructionError("Relay traces hold NaN/inf; drop those traces or bins first.")
        P = tr.shape[0]
        self.traces = tr
        for name in ("L", "D", "nL", "nD"):
            a = np.asarray(getattr(self, name), float)
            if a.shape != (P, 3) or not np.all(np.isfinite(a)):
                raise ReconstructionError(f"Relay field '{name}' must be ({P}, 3) finite; got {a.shape}.")
            setattr(self, name, a)
        for name in ("leg", "gain"):
            a = np.broadcast_to(np.asarray(getattr(self, name), float), (P,)).copy()
            if not np.all(np.isfinite(a)):
                raise ReconstructionError(f"Relay field '{name}' must be finite.")
            setattr(self, name, a)
        fp = np.zeros((P, 2)) if self.footprint is None else np.asarray(self.footprint, float)
        if fp.shape != (P, 2) or not np.all(np.isfinite(fp)) or np.any(fp < 0):
            raise ReconstructionError(f"Relay field 'footprint' must be ({P}, 2) finite variances >= 0 (m^2); "
                                      f"got shape {fp.shape}.")
        self.footprint = fp
        if self.frame is None:
            self.frame = plane_frame(np.vstack([self.L, self.D]),
                                     None if P == 0 else np.vstack([self.L, self.D]).mean(0)
                                     + np.mean(np.vstack([self.nL, self.nD]), axis=0))
        return self

    @property
    def n_traces(self) -> int:
        return self.traces.shape[0]

    def subset(self, idx) -> "Relay":
        """The relay restricted to traces ``idx`` (same frame)."""
        idx = np.asarray(idx)
        sig = self.sigma
        if isinstance(sig, np.ndarray) and sig.ndim >= 1 and sig.shape[0] == self.n_traces:
            sig = sig[idx]
        return Relay(self.traces[idx], self.grid, self.L[idx], self.D[idx], self.nL[idx],
                     self.nD[idx], self.leg[idx], self.gain[idx], sig, self.irf,
                     self.confocal, self.frame, dict(self.meta), self.footprint[idx])

    def window(self, t_lo: float, t_hi: float) -> "Relay":
        """The relay with its time axis cut to the bins inside [t_lo, t_hi)."""
        g = self.grid
        k0 = max(int(np.floor((t_lo - g.start) / g.bin_width)), 0)
        k1 = min(int(np.ceil((t_hi - g.start) / g.bin_width)), g.n_bins)
        if k1 - k0 < 2:
            raise ReconstructionError(f"The time window [{t_lo:.4g}, {t_hi:.4g}) m holds fewer than 2 "
                                      f"bins of the grid [{g.start:.4g}, {g.end:.4g}) m.")
        sig = self.sigma
        if isinstance(sig, np.ndarray) and sig.ndim == 2:
            sig = sig[:, k0:k1]
        grid = TimeGrid(g.start + k0 * g.bin_width, g.bin_width, k1 - k0)
        return Relay(self.traces[:, k0:k1], grid, self.L, self.D, self.nL, self.nD, self.leg,
                     self.gain, sig, self.irf, self.confocal, self.frame, dict(self.meta), self.footprint)


def _capture_sigma(capture):
    nz = capture.noise or {}
    model = str(nz.get("model", "")).lower()
    if model == "gaussian" and "sigma" in nz:
        return float(np.asarray(nz["sigma"]).ravel()[0])
    return None  # Poisson / unknown: the estimators use the counts themselves


def from_capture(capture) -> Relay:
    """The relay description of a paired or confocal relay-wall ``Capture`` (or a full STIR
    whose visible points are known). Raises ``ReconstructionError`` when wall points are absent."""
    from ..irf import from_samples

    if capture.illuminated_xyz is None or capture.observed_xyz is None:
        raise ReconstructionError(
            "NLOS reconstruction needs the relay points: the capture has no illuminated_xyz / "
            "observed_xyz. Import with a format that gives them (stanford-lct, ccsocr, general-nlos, "
            "ytal) or set them on the Capture.")
    tr, pairs = capture.as_pairs()
    ill, obs = capture.ill_ids(), capture.obs_ids()
    li = {int(v): k for k, v in enumerate(ill)}
    oi = {int(v): k for k, v in enumerate(obs)}
    try:
        L = capture.illuminated_xyz[[li[int(p)] for p in pairs[:, 0]]]
        D = capture.observed_xyz[[oi[int(p)] for p in pairs[:, 1]]]
    except KeyError as exc:
        raise ReconstructionError(f"A pair names patch id {exc} that the capture's ids do not hold.") from exc
    P = np.vstack([capture.illuminated_xyz, capture.observed_xyz])
    c, u, v, w = plane_frame(P)
    # the hidden scene lies on the side away from the source/camera when they are known
    if capture.source_xyz is not None and (capture.source_xyz - c) @ w > 0:
        w, v = -w, -v
    leg = np.zeros(len(tr))
    if capture.legs_included:
        if capture.source_xyz is None or capture.camera_xyz is None:
            raise ReconstructionError("A capture with legs_included=True needs source_xyz and camera_xyz "
                                      "to remove the legs; rectify it or give both points.")
        leg = np.linalg.norm(L - capture.source_xyz, axis=1) + np.linalg.norm(D - capture.camera_xyz, axis=1)
    resid = capture.extras.get("rectify_residual_m") if isinstance(capture.extras, dict) else None
    if resid is not None:  # grid time = true time - residual: a path at true t appears at t - resid
        leg = leg - np.asarray(resid, float)
    irf = None
    if capture.irf is not None:
        irf = from_samples(capture.irf, capture.grid.bin_width)
    confocal = bool(np.allclose(L, D, atol=1e-9))
    nrm = np.tile(w, (len(tr), 1))
    return Relay(tr, capture.grid, L, D, nrm, nrm.copy(), leg, np.ones(len(tr)),
                 _capture_sigma(capture), irf, confocal, (c, u, v, w),
                 {"provenance": dict(capture.provenance or {})})


def from_stir(stir: np.ndarray, grid: TimeGrid, ill_xyz, obs_xyz, ill_normals, obs_normals,
              source_xyz=None, camera_xyz=None, gain=None, sigma=None, irf=None,
              towards=None) -> Relay:
    """A relay from a full STIR (n_ill, n_obs, T) whose visible patches are known (Fig. 13).

    ``gain`` (n_ill, n_obs) is f(L) f(D) per pair (e.g. rho_i rho_j / pi^2 for Lambertian
    visible patches). With ``source_xyz`` / ``camera_xyz`` the legs are added to every path.
    ``towards`` is a point on the hidden side used to orient the relay normal ``w``.
    """
    stir = np.asarray(stir, float)
    ni, no, nb = stir.shape
    ii, jj = np.meshgrid(np.arange(ni), np.arange(no), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    L, D = np.asarray(ill_xyz, float)[ii], np.asarray(obs_xyz, float)[jj]
    leg = np.zeros(len(ii))
    if source_xyz is not None:
        leg = leg + np.linalg.norm(L - np.asarray(source_xyz, float), axis=1)
    if camera_xyz is not None:
        leg = leg + np.linalg.norm(D - np.asarray(camera_xyz, float), axis=1)
    g = np.ones(len(ii)) if gain is None else np.asarray(gain, float).reshape(ni, no)[ii, jj]
    sig = sigma
    if isinstance(sigma, np.ndarray) and sigma.shape[:2] == (ni, no):
        sig = sigma.reshape(ni * no, -1)
    frame = plane_frame(np.vstack([ill_xyz, obs_xyz]), towards)
    return Relay(stir.reshape(ni * no, nb), grid, L, D, np.asarray(ill_normals, float)[ii],
                 np.asarray(obs_normals, float)[jj], leg, g, sig, irf, False, frame, {})


@dataclass
class ConfocalGrid:
    """A confocal scan on a regular square grid of the relay plane: ``data[iy, ix, t]``.

    ``x``, ``y`` are the in-plane coordinates (metres, along ``u``, ``v`` from ``centre``)."""

    data: np.ndarray
    x: np.ndarray
    y: np.ndarray
    grid: TimeGrid
    frame: tuple

    @property
    def half_width(self) -> float:
        return 0.5 * max(self.x[-1] - self.x[0], self.y[-1] - self.y[0])


def confocal_grid(relay: Relay, tol: float = 1e-3) -> ConfocalGrid:
    """Arrange a confocal relay on its regular wall grid (LCT and f-k need one).

    Raises ``ReconstructionError`` when the scan is not confocal, not planar, not square or not
    regular (within ``tol`` of a grid step)."""
    if not relay.confocal:
        raise ReconstructionError("LCT and f-k migration need a confocal scan (laser and detector on "
                                  "the same wall point); use method='bp' for paired scans.")
    if np.any(relay.leg != 0):
        raise ReconstructionError("LCT and f-k migration need rectified traces (t = 0 at the wall); "
                                  "this relay carries legs. Use method='bp', which removes them.")
    c, u, v, w = relay.frame
    rel = relay.L - c
    h = rel @ w
    span = np.ptp(rel @ u)
    if np.max(np.abs(h)) > max(1e-2 * span, 1e-6):
        raise ReconstructionError(f"LCT and f-k migration need a planar wall; the scan points leave "
                                  f"its plane by up to {np.max(np.abs(h)):.3g} m. Use method='bp'.")
    a, b = rel @ u, rel @ v

    def axis(q):
        vals = np.unique(np.round(q / max(span, 1e-9) / tol) * tol * max(span, 1e-9))
        return vals

    # The grid's coordinates are the positions rounded to multiples of tol * span (up to half of
    # that off; kept: the exact means move the initialiser's maps by < 0.1 mm, which flips
    # knife-edge decisions of the surface fit, e.g. step 4a's split of surface_coverage seed 513).
    xa, ya = axis(a), axis(b)
    n = len(xa)
    if len(ya) != n or n * n != relay.n_traces or n < 2:
        raise ReconstructionError(f"LCT and f-k migration need a full square N x N scan grid; got "
                                  f"{len(xa)} x {len(ya)} distinct positions for {relay.n_traces} traces.")
    step = (xa[-1] - xa[0]) / (n - 1)
    ix = np.clip(np.rint((a - xa[0]) / step).astype(int), 0, n - 1)
    iy = np.clip(np.rint((b - ya[0]) / step).astype(int), 0, n - 1)
    # evenness is judged on the members' mean coordinates: the rounded ones of a scan summed in
    # blocks (``subsample_confocal``) alternate by one rounding step (50.4 / 51.2 mm)
    cx = np.bincount(ix, a, n) / np.maximum(np.bincount(ix, minlength=n), 1)
    cy = np.bincount(iy, b, n) / np.maximum(np.bincount(iy, minlength=n), 1)
    step_c = (cx[-1] - cx[0]) / (n - 1)
    if np.max(np.abs(np.diff(cx) - step_c)) > tol * span or np.max(np.abs(np.diff(cy) - step_c)) > tol * span:
        raise ReconstructionError("LCT and f-k migration need an evenly spaced square scan grid "
                                  "with equal steps along both axes.")
    if np.any(np.bincount(iy * n + ix, minlength=n * n) != 1):
        raise ReconstructionError("LCT and f-k migration need one trace per scan grid point; some "
                                  "point of this scan holds two traces and another none.")
    data = np.zeros((n, n, relay.grid.n_bins), dtype=np.float32)
    data[iy, ix] = relay.traces
    return ConfocalGrid(data, xa, ya, relay.grid, relay.frame)
