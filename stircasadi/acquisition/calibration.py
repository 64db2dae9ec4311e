"""Calibration of measured captures: time zero, impulse response, background, pile-up.

When to use: after ``acquire`` or ``import`` and before estimation. Each function returns a
new ``Capture`` (the input is not modified) and records what it did, with its numbers, in the
group ``calibration/`` of the file (``Capture.extras['calibration']``), so an estimate can always
be traced back to the corrections applied.

Equations
---------
* **Time zero.** The first-bounce return of trace ``p`` peaks at ``tau_p`` (first local peak above
  ``frac`` of the trace maximum, refined by a parabola through three bins). Given the path
  lengths ``L_p`` those returns must have (source -> patch -> camera, from the geometry), the
  instrument's offset is ``delta = median_p(tau_p - L_p)`` and the grid start becomes
  ``start - delta``. (The impulse response is taken as centred, as DESIGN.md section 4 requires.)
* **Impulse response.** ``stircasadi.irf.estimate_samples``: the first-bounce windows of the
  traces (``2h+1`` bins around each peak), aligned on their peak bins, averaged and normalised
  to unit sum; the peak sits at the centre.
* **Background.** Per trace, the median of the bins of a window before the first return is
  subtracted (dark counts, ambient light, scope offset).
* **Pile-up / dead time** (photon counters, Coates 1968): with ``N`` sync periods and ``n_k``
  counts in bin ``k``, the detector was armed in ``A_k = N - sum_{j in D(k)} n_j`` periods, where
  ``D(k)`` are the earlier bins within the dead time (all earlier bins for classic TCSPC, whose
  dead time exceeds the period). The per-period detection probability is ``n_k / A_k`` and the
  mean photon number ``lambda_k = -ln(1 - n_k / A_k)``; the corrected histogram is ``N lambda_k``.

Neglects: a time-varying offset (drift) and a trace-dependent impulse response.
"""
from __future__ import annotations

import dataclasses
import datetime as _dt

import numpy as np

from ..capture import Capture
from ..errors import CaptureError
from ..irf import estimate_samples


def _record(cap: Capture, step: str, **values) -> dict:
    extras = dict(cap.extras)
    calib = dict(extras.get("calibration", {"__attrs__": {}}))
    attrs = dict(calib.get("__attrs__", {}))
    steps = [s for s in str(attrs.get("steps", "")).split(",") if s]
    steps.append(step)
    attrs["steps"] = ",".join(steps)
    attrs[f"{step}_date"] = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    for k, v in values.items():
        attrs[f"{step}_{k}"] = v
    calib["__attrs__"] = attrs
    extras["calibration"] = calib
    return extras


def _replace(cap: Capture, data: np.ndarray, **kw) -> Capture:
    if cap.stir is not None:
        return dataclasses.replace(cap, stir=data.reshape(cap.stir.shape), **kw)
    return dataclasses.replace(cap, traces=data.reshape(cap.traces.shape), **kw)


def first_peaks(traces: np.ndarray, frac: float = 0.3, window: int = 12) -> np.ndarray:
    """Sub-bin index of the first local peak above ``frac * max`` of each trace (NaN if none)."""
    tr = np.atleast_2d(np.asarray(traces, dtype=float))
    out = np.full(tr.shape[0], np.nan)
    for p, y in enumerate(tr):
        m = y.max()
        if not m > 0:
            continue
        above = np.flatnonzero(y >= frac * m)
        k0 = above[0]
        seg = y[k0:k0 + window]
        k = k0 + int(np.argmax(seg))
        if 0 < k < y.size - 1:
            a, b, c = y[k - 1], y[k], y[k + 1]
            den = a - 2 * b + c
            out[p] = k + (0.5 * (a - c) / den if den < 0 else 0.0)
        else:
            out[p] = float(k)
    return out


def time_zero(cap: Capture, expected_first_m, frac: float = 0.3, window: int = 12) -> Capture:
    """Shift the time axis so the first-bounce peaks sit at the expected path lengths.

    ``expected_first_m`` : scalar or one value per trace (``as_pairs`` order), metres of path.
    """
    traces, _ = cap.as_pairs()
    peaks = first_peaks(traces, frac, window)
    exp = np.broadcast_to(np.asarray(expected_first_m, dtype=float), peaks.shape)
    ok = np.isfinite(peaks) & np.isfinite(exp)
    if not ok.any():
        raise CaptureError("time_zero: no trace has a first-bounce peak (all traces are <= 0); "
                           "cannot calibrate the time origin.")
    tau = cap.grid.start + (peaks[ok] + 0.5) * cap.grid.bin_width
    delta = float(np.median(tau - exp[ok]))
    spread = float(np.std(tau - exp[ok]))
    grid = dataclasses.replace(cap.grid, start=cap.grid.start - delta)
    return dataclasses.replace(cap, grid=grid, extras=_record(cap, "time_zero", shift_m=delta,
                                                             spread_m=spread, n_traces=int(ok.sum())))


def estimate_irf(cap: Capture, half_width: int = 8, frac: float = 0.3) -> Capture:
    """Estimate the impulse response from the first-bounce returns; stored in ``cap.irf``."""
    traces, _ = cap.as_pairs()
    irf = estimate_samples(traces, half_bins=half_width, frac=frac, trim=False)
    n = int(np.isfinite(first_peaks(traces, frac)).sum())
    if irf is None:
        raise CaptureError(f"estimate_irf: no first-bounce return with {half_width} bins on both "
                           "sides; reduce half_width or check the traces.")
    return dataclasses.replace(cap, irf=irf, extras=_record(cap, "irf", half_width=half_width,
                                                           n_traces=n))


def subtract_background(cap: Capture, n_bins: int | None = None, frac: float = 0.3,
                        margin: int = 5) -> Capture:
    """Subtract each trace's median over the bins before its first return.

    ``n_bins``: the window is bins ``[0, n_bins)``; default: up to ``margin`` bins before the
    earliest first peak of all traces.
    """
    traces, _ = cap.as_pairs()
    if n_bins is None:
        pk = first_peaks(traces, frac)
        if not np.isfinite(pk).any():
            raise CaptureError("subtract_background: no return found; give n_bins explicitly.")
        n_bins = int(np.nanmin(pk)) - margin
    if not 1 <= n_bins < cap.n_bins:
        raise CaptureError(f"subtract_background: the window must hold 1..{cap.n_bins - 1} bins before "
                           f"the first return; got {n_bins}. Pass n_bins explicitly.")
    level = np.median(traces[:, :n_bins], axis=1, keepdims=True)
    out = traces - level
    return _replace(cap, out, extras=_record(cap, "background", window_bins=int(n_bins),
                                             mean_level=float(level.mean())))


def coates(counts: np.ndarray, n_sync: int, dead_bins: int | None = None) -> np.ndarray:
    """Pile-up / dead-time correction of TCSPC histograms (time last); see the module docstring."""
    n = np.asarray(counts, dtype=float)
    if not np.all(np.isfinite(n)) or (n < 0).any():
        raise CaptureError("coates: counts must be finite and >= 0.")
    if not n_sync >= 1:
        raise CaptureError(f"coates: n_sync (sync periods) must be >= 1; got {n_sync!r}.")
    c = np.cumsum(n, axis=-1)
    before = np.concatenate([np.zeros(n.shape[:-1] + (1,)), c[..., :-1]], axis=-1)
    if dead_bins is not None:
        d = int(dead_bins)
        lagged = np.concatenate([np.zeros(n.shape[:-1] + (d + 1,)), c[..., :-1]], axis=-1)[..., :n.shape[-1]]
        before = before - lagged
    armed = n_sync - before
    if (armed <= n).any():
        raise CaptureError("coates: a bin holds as many counts as periods armed; the histogram is "
                           "saturated (or n_sync is wrong) and cannot be corrected.")
    return -n_sync * np.log1p(-n / armed)


def pileup_correct(cap: Capture, n_sync: int | None = None, dead_bins: int | None = None) -> Capture:
    """Apply :func:`coates` to a counting capture (``n_sync`` defaults to ``noise['shots']``)."""
    if n_sync is None:
        n_sync = cap.noise.get("shots")
        if n_sync is None:
            raise CaptureError("pileup_correct: the capture does not record its sync periods "
                               "(noise/shots); pass n_sync.")
    traces, _ = cap.as_pairs()
    out = coates(traces, int(n_sync), dead_bins)
    return _replace(cap, out, extras=_record(cap, "pileup", n_sync=int(n_sync),
                                             dead_bins=-1 if dead_bins is None else int(dead_bins),
                                             max_correction=float(np.max(out / np.maximum(traces, 1)))))
