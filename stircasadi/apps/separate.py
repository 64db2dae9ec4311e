"""Direct/global separation: first bounce vs the rest, per patch, three ways.

When to use
-----------
To split what each patch shows into light that came straight from the source (direct: the
first bounce, source -> j -> camera) and light that reached it via other surfaces (global:
interreflections, hidden patches). Three routes, which check each other:

``separate_onsets`` (the STIR's own time structure, any capture)
    In the trace (j, j) (pulse aimed at j, j observed) the direct return is the earliest light:
    every other path s -> j -> k -> ... -> j -> c is longer by at least twice the distance to
    j's nearest neighbour. It is fitted as ``A * pulse(t - tau)`` (the binned impulse response,
    ``stircasadi.irf.Template``) over the leading edge and peak of the first return; direct =
    the fitted pulse, global = everything else the patch receives: under full illumination
    ``sum_i stir[i, j] - direct`` (a full STIR), or the rest of its own trace (confocal scans).
    Captures without an impulse response (or whose first return is cut by the grid start, as
    rectified relay-wall scans) use a *gate*: direct = the first family up to the valley before
    the next family rises (found on the trace summed over patches: after the first family has
    fallen below 1 % of its peak, the first rise of the running mean by 1.5x over its running
    minimum), minus a background taken as the mean of the last 10 % of each trace.

``separate_nayar`` (Nayar et al. 2006, emulated by superposition of the same STIR)
    Two complementary binary patterns P, P' (a checkerboard over a scan layout, else alternate
    ids): ``L+ = max(Y_P, Y_P')``, ``L- = min``; direct = L+ - L-, global = 2 L-.

``separate_bounces`` (the forward model, simulated scenes)
    ``simulate(..., per_bounce=True)``: direct = the first-bounce STIR at (j, j).

Stated errors
-------------
* onsets: the global light of trace (j, j) starts at tau2 >= tau + 2 d_min (d_min: distance to
  j's nearest facing patch). The fit window ends at t_end (the first return's peak), so the
  global light inside it is at most ``G_jj H(t_end - tau2)`` (H: the impulse response's
  cumulative), and the fitted amplitude exceeds the direct by at most ``c`` times that, with
  ``c = max(p) / <p, p>`` for the binned pulse p. The fit absorbs that excess from the global it
  reports (G_true = G + dA), hence

      error_bound = c H G / (1 - c H) + 4 sigma / sqrt(<p, p>)      (c H < 1; else unresolved)

  with tau2 the first rise of the fit residual above 1e-3 of its maximum (a Gaussian pulse is
  at 1e-3 of its peak 3.7 sigma before its centre) and sigma the noise std. It is IRF-limited:
  negligible when 2 d_min exceeds a few response widths, vacuous (``unresolved`` in the
  metadata, bound = the direct itself) when the second family starts under the direct pulse.
  In gate mode the bound is the extrapolated tail of the first family past the gate plus the
  background's Poisson error.
* nayar: the two patterns light different halves, so route 2 returns
  ``D + (G_on - G_off)``: its error is the pattern imbalance of the global light, small only
  when the global light varies slowly across the pattern (Nayar's high-frequency condition).
  ``imbalance`` in the result is ``|D_nayar - D_onsets|``.

What it neglects: a first return that is not one impulse-response-shaped pulse (an extended or
strongly tilted patch broadens it), pile-up and afterpulsing of photon counters.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from ..errors import CaptureError, SensorError
from ..irf import IdealIRF, Template, from_samples
from ..timegrid import TimeGrid
from .relight import nayar_patterns, superpose

#: noise quantile of the stated direct error (4 sigma: exceeded with probability 6e-5 per patch)
Z_BOUND = 4.0
#: the global light's rise is where the fit residual after the first return exceeds this fraction
#: of its maximum (a Gaussian pulse reaches 1e-3 of its peak 3.7 sigma before its centre)
RISE_FRAC = 1e-3
#: gate mode: the next family starts where the running mean rises this factor above its running minimum
RISE_GATE = 1.5

__all__ = ["Separation", "separate_onsets", "separate_nayar", "separate_bounces", "separate_capture"]


@dataclass
class Separation:
    """Direct and global light per patch (time-integrated radiance; transients when known)."""

    ids: np.ndarray
    direct: np.ndarray
    global_: np.ndarray
    method: str
    grid: TimeGrid | None = None
    direct_transient: np.ndarray | None = None
    global_transient: np.ndarray | None = None
    onset: np.ndarray | None = None
    error_bound: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)


def _diag_traces(stir, ill_ids, obs_ids):
    ill_ids, obs_ids = np.asarray(ill_ids), np.asarray(obs_ids)
    both = np.array([j for j in obs_ids if j in set(ill_ids.tolist())], int)
    if not len(both):
        raise CaptureError("No patch is both lit and observed: the direct return of a patch is "
                           "in the trace with the pulse aimed at it, which this STIR lacks.")
    r = np.array([int(np.flatnonzero(ill_ids == j)[0]) for j in both])
    c = np.array([int(np.flatnonzero(obs_ids == j)[0]) for j in both])
    return both, r, c


def _noise_sigma(y, k_before):
    if k_before >= 12:
        seg = y[:k_before]
        return float(1.4826 * np.median(np.abs(seg - np.median(seg)))) or float(np.std(seg))
    d = np.diff(y)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2))


def _fit_direct(y, grid, tpl: Template, thr: float, sigma=None):
    """A, tau, window end, bound inputs for one trace's first return."""
    w, t = grid.bin_width, grid.centres
    m = float(np.max(y))
    if not m > 0:
        return None
    k_thr = int(np.flatnonzero(y >= thr * m)[0])
    span = max(2, int(math.ceil(3 * tpl.width / w)))
    k_pk = k_thr + int(np.argmax(y[k_thr:k_thr + span + 1]))
    lo = max(0, k_thr - int(math.ceil(5 * tpl.width / w)))
    hi = min(len(y), k_pk + 2)
    sl = slice(lo, hi)
    s = _noise_sigma(y, lo) if sigma is None else float(sigma)

    def amp(tau):
        p = tpl.pulse(t[sl] - tau)[0]
        pp = float(p @ p)
        return (float(p @ y[sl]) / pp if pp > 0 else 0.0), p, pp

    def cost(tau):
        a, p, _ = amp(tau)
        r = y[sl] - a * p
        return float(r @ r)

    res = minimize_scalar(cost, bounds=(t[k_pk] - 2 * tpl.width - w, t[k_pk] + 2 * w), method="bounded",
                          options={"xatol": 1e-10 * w})
    tau = float(res.x)
    A, p, pp = amp(tau)
    for _ in range(8):  # Gauss-Newton on (A, tau): Brent leaves tau ~1e-8 of a width off
        p, dp = tpl.pulse(t[sl] - tau)
        J = np.stack([p, -A * dp], axis=1)
        step = np.linalg.lstsq(J, y[sl] - A * p, rcond=None)[0]
        A, tau = A + step[0], tau + step[1]
        if abs(step[1]) < 1e-14 * tpl.width:
            break
    p = tpl.pulse(t[sl] - tau)[0]
    pp = float(p @ p)
    return A, tau, t[min(hi, len(t)) - 1] + 0.5 * w, s, pp, float(np.max(p))


def separate_onsets(stir: np.ndarray, grid: TimeGrid, ill_ids, obs_ids, irf=None,
                    sigma: float | None = None, threshold: float = 0.2,
                    illumination: str = "full") -> Separation:
    """Route 1 (module doc) on a full STIR ``(n_ill, n_obs, n_bins)``.

    ``irf``: impulse-response object (None or ideal: gate mode). ``illumination``: ``"full"``
    (global = everything the patch receives with every patch lit, Nayar's definition) or
    ``"self"`` (global = the rest of the patch's own trace).
    """
    if illumination not in ("full", "self"):
        raise CaptureError(f"illumination must be 'full' or 'self'; got {illumination!r}.")
    stir = np.asarray(stir, float)
    ids, r, c = _diag_traces(stir, ill_ids, obs_ids)
    traces = stir[r, c]
    total = stir[:, c].sum(axis=0) if illumination == "full" else traces
    sep = separate_traces(traces, grid, irf=irf, sigma=sigma, threshold=threshold)
    sep.ids = ids
    sep.global_transient = total - sep.direct_transient
    sep.global_ = sep.global_transient.sum(axis=1)
    sep.metadata["illumination"] = illumination
    return sep


def separate_traces(traces: np.ndarray, grid: TimeGrid, irf=None, sigma: float | None = None,
                    threshold: float = 0.2) -> Separation:
    """Route 1 on traces (n, n_bins) whose first return is the direct one (confocal (i, i),
    or the diagonal of a STIR); global = the rest of each trace."""
    traces = np.atleast_2d(np.asarray(traces, float))
    if traces.shape[-1] != grid.n_bins:
        raise CaptureError(f"traces must have {grid.n_bins} bins (the grid's); got {traces.shape}.")
    if irf is None or isinstance(irf, IdealIRF):
        return _gate(traces, grid)
    tpl = Template(irf, grid.bin_width)
    n = len(traces)
    D = np.zeros_like(traces)
    tau, bound = np.full(n, np.nan), np.full(n, np.nan)
    for k, y in enumerate(traces):
        fit = _fit_direct(y, grid, tpl, threshold, sigma)
        if fit is None:
            continue
        A, tau[k], t_end, s, pp, pmax = fit
        D[k] = A * tpl.pulse(grid.centres - tau[k])[0]
        res = y - D[k]
        k_end = int(np.searchsorted(grid.edges, t_end)) - 1
        after = res[k_end:]
        det = np.flatnonzero(after > max(Z_BOUND * s, RISE_FRAC * float(after.max(initial=0.0))))
        tau2 = grid.edges[k_end + det[0]] if len(det) else grid.end
        G = max(float(res.sum()), 0.0)
        leak = float(irf.cdf(np.array([t_end - tau2]))[0])
        cl = leak * pmax / pp
        # the fit absorbs dA >= 0 of the global light, so G_true = G + dA:
        # dA <= cl (G + dA)  =>  dA <= cl G / (1 - cl); no bound (unresolved) when cl >= 1
        bias = cl * G / (1.0 - cl) if cl < 1.0 else abs(A)
        bound[k] = bias + Z_BOUND * s / math.sqrt(pp) + 1e-12 * abs(A)
    direct = D.sum(axis=1)
    unresolved = np.flatnonzero(bound >= np.abs(direct))
    return Separation(ids=np.arange(n), direct=direct, global_=(traces - D).sum(axis=1),
                      method="onsets", grid=grid, direct_transient=D, global_transient=traces - D,
                      onset=tau, error_bound=bound,
                      metadata={"mode": "template", "threshold": threshold, "irf": irf.describe(),
                                "unresolved": unresolved.tolist()})


def _gate(traces, grid, background_frac: float = 0.1) -> Separation:
    """Gate mode: the first family up to the valley of the summed trace, background removed."""
    S = traces.sum(axis=0)
    k0 = int(np.argmax(S >= 0.2 * S.max()))
    k_pk = k0 + int(np.argmax(S[k0:k0 + max(8, grid.n_bins // 50)]))
    nb = max(4, int(background_frac * grid.n_bins))
    b = np.mean(traces[:, -nb:], axis=1)   # mean, not median: photon counts below one per bin
    Sb = S - b.sum()
    # valley: after the first family has fallen below 1 % of its peak, the lowest point of the
    # running mean before the next family's maximum (or the background, if none rises again)
    from scipy.ndimage import uniform_filter1d

    sm = uniform_filter1d(Sb, size=max(9, grid.n_bins // 100), mode="nearest")
    below = np.flatnonzero(sm[k_pk:] < 1e-2 * sm[k_pk])
    k1 = min(k_pk + (int(below[0]) if len(below) else 1), grid.n_bins - 2)
    runmin = np.minimum.accumulate(sm[k1:])
    rise = np.flatnonzero(sm[k1:] > RISE_GATE * np.maximum(runmin, 1e-300))
    if len(rise):   # the next family: gate at the valley before it
        gate = k1 + int(np.argmin(sm[k1:k1 + int(rise[0])]))
    else:           # none: where the first family has decayed to 1.1 x the final level
        flat = np.flatnonzero(sm[k1:] <= 1.1 * max(sm[-nb:].mean(), 1e-300))
        gate = k1 + (int(flat[0]) if len(flat) else 0)
    y = traces - b[:, None]
    D = np.zeros_like(traces)
    D[:, :gate] = y[:, :gate]
    # tail of the first family past the gate: exponential extrapolation of its last decade
    seg = np.clip(sm[k_pk:gate], 1e-300, None)
    tail_frac = 0.0
    if gate - k_pk > 4 and seg[0] > seg[-1] > 0:
        rate = math.log(seg[0] / seg[-1]) / (gate - k_pk)
        tail_frac = float(seg[-1] / (math.expm1(rate) if rate > 0 else 1.0) / max(Sb[:gate].sum(), 1e-300))
    direct = D.sum(axis=1)
    bound = tail_frac * np.abs(direct) + np.sqrt(np.maximum(b, 0) * grid.n_bins)
    return Separation(ids=np.arange(len(traces)), direct=direct, global_=(y - D).sum(axis=1),
                      method="onsets", grid=grid, direct_transient=D, global_transient=y - D,
                      onset=np.full(len(traces), grid.centres[k_pk]), error_bound=bound,
                      metadata={"mode": "gate", "gate_bin": int(gate), "gate_m": float(grid.edges[gate]),
                                "background_per_bin": b, "tail_fraction": tail_frac})


def separate_nayar(stir: np.ndarray, grid: TimeGrid, ill_ids, obs_ids, layout=None,
                   reference: Separation | None = None) -> Separation:
    """Route 2 (module doc): two complementary patterns emulated by superposition of the STIR."""
    ids, r, c = _diag_traces(stir, ill_ids, obs_ids)
    p1, p2 = nayar_patterns(ill_ids, layout)
    a = superpose(stir, grid, ill_ids, obs_ids, p1)
    b = superpose(stir, grid, ill_ids, obs_ids, p2)
    hi = np.maximum(a.steady, b.steady)[c]
    lo = np.minimum(a.steady, b.steady)[c]
    meta = {"patterns": [p1.weights.tolist(), p2.weights.tolist()]}
    sep = Separation(ids=ids, direct=hi - lo, global_=2 * lo, method="nayar", grid=grid, metadata=meta)
    if reference is not None:
        sep.error_bound = np.abs(sep.direct - reference.direct)
        meta["imbalance_vs"] = reference.method
    return sep


def separate_bounces(scene, grid: TimeGrid, sensor=None, bounces: int | None = None,
                     allow_truncation: bool = False) -> Separation:
    """Route 3 (module doc): the forward model's own bounce decomposition of a simulated scene."""
    from ..transport import needed_bounces, simulate

    K = needed_bounces(scene) if bounces is None else int(bounces)
    tr = simulate(scene, grid, sensor=sensor, method="bounces", bounces=K, per_bounce=True,
                  allow_truncation=allow_truncation)
    ids, r, c = _diag_traces(tr.stir, tr.ill_ids, tr.obs_ids)
    D = tr.per_bounce[0][r, c]
    G = tr.stir[:, c].sum(axis=0) - D
    return Separation(ids=ids, direct=D.sum(axis=1), global_=G.sum(axis=1), method="bounces", grid=grid,
                      direct_transient=D, global_transient=G, metadata={"bounces": K})


def separate_capture(capture, threshold: float = 0.2, sigma: float | None = None) -> Separation:
    """Route 1 on a Capture: full STIR (global under full illumination) or paired traces whose
    pairs (i, i) hold the direct returns (confocal scans; global = the rest of each trace)."""
    irf = None
    if capture.irf is not None:
        try:
            irf = from_samples(capture.irf, capture.grid.bin_width)
        except SensorError:
            irf = None
    if sigma is None and capture.noise.get("model") == "gaussian":
        sigma = capture.noise.get("sigma")
    if capture.is_full:
        return separate_onsets(capture.stir, capture.grid, capture.ill_ids(), capture.obs_ids(),
                               irf=irf, sigma=sigma, threshold=threshold)
    same = capture.pairs[:, 0] == capture.pairs[:, 1]
    if not same.any():
        raise CaptureError("This capture's traces pair different illuminated and observed points "
                           "(a non-confocal scan): no trace holds a point's own first bounce, so the "
                           "direct return cannot be separated. A confocal scan or a full STIR is needed.")
    sep = separate_traces(capture.traces[same], capture.grid, irf=irf, sigma=sigma, threshold=threshold)
    sep.ids = capture.pairs[same, 0]
    sep.metadata["illumination"] = "self (confocal: the rest of each point's own trace)"
    return sep
