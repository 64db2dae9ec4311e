"""Time profiles of the most informative traces, with the fitted model and its residuals.

When to use: after a capture (and an estimate): ``stircasadi run``, ``stircasadi plot``,
notebooks. The traces are chosen from the data alone (``informative_traces``):

* every trace is matched-filtered with the capture's impulse response (its samples, else a
  3-bin Gaussian), and the returns above ``k_sigma`` noise std are its *families*, earliest first
  (noise std: ``stircasadi.view.noise_from_data`` unless given);
* in trace (i, j) with i != j the earliest family is the second bounce i -> j, in trace (i, i)
  the first bounce; every later family carries a third (or higher) bounce;
* the strongest second bounces and the strongest later returns (by matched-filter SNR) are the
  traces drawn (one of a trace and its reciprocal), so a scene whose fixed first pairs hold no
  second bounce still shows one.

``profiles_figure`` draws each chosen trace on a symmetric-log axis (linear within 3 noise std,
so noise and a 1e-6 return both show) with the model (the joint fit's ``model.simulate`` or a
render of the estimate) and, below it, the whitened residual (data - model) / sigma with the
+-3 band. Nothing here fits anything; neglects: families closer than one impulse-response width
are one family.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .common import new_figure

__all__ = ["Trace", "informative_traces", "profiles_figure", "capture_traces"]


@dataclass
class Trace:
    """One chosen trace: pulse at ``ill`` seen at ``obs`` (patch ids), its row in the capture's
    trace stack, why it was chosen, its families (times, SNR) and the family that chose it."""

    ill: int
    obs: int
    row: int
    why: str
    times: np.ndarray
    snr: np.ndarray
    family: int


def capture_traces(capture):
    """(Y (n_traces, n_bins), pairs (n_traces, 2) of (illuminated id, observed id))."""
    if capture.stir is not None:
        ill, obs = capture.ill_ids(), capture.obs_ids()
        pairs = np.array([(i, j) for i in ill for j in obs], int).reshape(-1, 2)
        return capture.stir.reshape(-1, capture.grid.n_bins), pairs
    return np.asarray(capture.traces), np.asarray(capture.pairs, int)


def _kernel(capture) -> np.ndarray:
    """Unit-norm matched filter: the capture's impulse response samples, else a 3-bin Gaussian."""
    h = None if capture.irf is None else np.asarray(capture.irf, float)
    if h is None or h.size < 2 or not np.isfinite(h).all() or h.max() <= 0:
        x = np.arange(-6, 7)
        h = np.exp(-0.5 * (x / 1.3) ** 2)
    h = np.clip(h, 0.0, None)
    keep = np.flatnonzero(h > 1e-3 * h.max())
    h = h[keep[0]:keep[-1] + 1]
    return h / np.linalg.norm(h)


def _families(s: np.ndarray, sigma: float, k_sigma: float, sep: int):
    """Peak indices of the filtered trace ``s`` above k_sigma * sigma, at least ``sep`` bins apart."""
    if sigma <= 0 or s.size < 3:
        return np.zeros(0, int)
    above = s > k_sigma * sigma
    loc = np.flatnonzero(above[1:-1] & (s[1:-1] >= s[:-2]) & (s[1:-1] > s[2:])) + 1
    keep = []
    for k in loc[np.argsort(-s[loc])]:
        if all(abs(k - q) >= sep for q in keep):
            keep.append(int(k))
    return np.array(sorted(keep), int)


def informative_traces(capture, sigma: float | None = None, n_second: int = 2, n_later: int = 2,
                       k_sigma: float = 6.0) -> tuple[list, float]:
    """The traces with the strongest second bounces and later (third-bounce) returns.

    Returns (list of ``Trace``, the noise std used). Falls back to the strongest traces when no
    second bounce or later return is detected."""
    from ..view import noise_from_data

    Y, pairs = capture_traces(capture)
    sig = float(sigma) if sigma else noise_from_data(Y)
    h = _kernel(capture)
    fwhm = max(int(np.sum(h >= 0.5 * h.max())), 1)
    sep = max(2 * fwhm, 3)
    fam = []
    for r in range(Y.shape[0]):
        s = np.correlate(Y[r], h, mode="same")
        k = _families(s, sig if sig > 0 else 1e-30 * (np.abs(s).max() or 1.0), k_sigma, sep)
        fam.append((capture.grid.centres[k], s[k] / (sig or 1.0)))
    second, later = [], []
    for r, (i, j) in enumerate(pairs):
        t, z = fam[r]
        if len(t) and i != j:
            second.append((float(z[0]), r, 0))
        for f in range(1, len(t)):
            later.append((float(z[f]), r, f))
    out, used = [], set()

    def take(cands, n, why):
        for z, r, f in sorted(cands, reverse=True):
            if len([o for o in out if o.why == why]) >= n:
                break
            key = frozenset(int(v) for v in pairs[r])   # (i, j) and its reciprocal (j, i): one
            if key in used:
                continue
            used.add(key)
            out.append(Trace(int(pairs[r][0]), int(pairs[r][1]), r, why, fam[r][0], fam[r][1], f))
    take(second, n_second, "second bounce")
    take(later, n_later, "later return")
    if not out:  # nothing detected: the strongest traces
        peak = np.max(np.abs(Y), axis=1)
        for r in np.argsort(-peak)[:max(n_second + n_later, 1)]:
            out.append(Trace(int(pairs[r][0]), int(pairs[r][1]), int(r), "strongest trace",
                             fam[r][0], fam[r][1], -1))
    return out, sig


def _ordinal(i: int, j: int, f: int) -> str:
    """Which bounce family f of trace (i, j) is, as far as the trace's order tells."""
    if f == 0:
        return "1st bounce" if i == j else "2nd bounce"
    return "3rd+ bounce"


def profiles_figure(capture, model=None, sigma: float | None = None, names: dict | None = None,
                    traces: list | None = None, title: str = "", model_label: str = "model (fit)",
                    fig=None):
    """Figure of the chosen traces (``informative_traces``): data, model, residual / sigma.

    capture : the Capture (full STIR or paired traces).
    model : the model STIR (n_ill, n_obs, n_bins) on the capture's grid and ids, or paired
        traces (n_pairs, n_bins), or None (data only).
    names : {patch id: label} for the panel titles.
    """
    sel, sig = (traces, float(sigma)) if traces is not None and sigma else informative_traces(capture, sigma)
    Y, pairs = capture_traces(capture)
    Mt = None
    if model is not None:
        Mt = np.asarray(model, float).reshape(-1, Y.shape[1])
        if Mt.shape != Y.shape:
            raise ValueError(f"the model has {Mt.shape[0]} traces of {Mt.shape[1]} bins; the capture "
                             f"{Y.shape[0]} of {Y.shape[1]}")
    t = capture.grid.centres
    n = len(sel)
    ncol = 2 if n > 1 else 1
    nrow = int(np.ceil(n / ncol))
    fig = new_figure(fig, (6.2 * ncol, (4.6 if Mt is not None else 3.4) * nrow + 0.8))
    outer = fig.add_gridspec(nrow, ncol, hspace=0.32, wspace=0.25)
    nm = names or {}
    h = _kernel(capture)
    half = len(h) * capture.grid.bin_width
    for k, tr in enumerate(sel):
        r, c = divmod(k, ncol)
        cell = outer[r, c].subgridspec(2 if Mt is not None else 1, 1, hspace=0.06,
                                       height_ratios=[3, 1] if Mt is not None else None)
        ax = fig.add_subplot(cell[0])
        y = Y[tr.row]
        lo = (tr.times.min() if len(tr.times) else t[np.argmax(np.abs(y))]) - 3 * half
        hi = (tr.times.max() if len(tr.times) else t[np.argmax(np.abs(y))]) + 3 * half
        win = (t >= lo) & (t <= hi)
        ax.plot(t[win], y[win], color="0.25", lw=1.0, label="data")
        if Mt is not None:
            ax.plot(t[win], Mt[tr.row][win], color="#d62728", lw=1.2, alpha=0.85, label=model_label)
        ax.axhspan(-3 * sig, 3 * sig, color="0.85", zorder=0, label="±3σ noise")
        _symlog(ax, sig, max(float(np.max(y[win])), float(np.max(Mt[tr.row][win])) if Mt is not None else 0.0))
        for f, (tf, zf) in enumerate(zip(tr.times, tr.snr)):
            ax.axvline(tf, color="#1f77b4" if f == tr.family else "0.6", lw=0.8, ls=":")
            ax.annotate(f"{_ordinal(tr.ill, tr.obs, f)}\nSNR {zf:.0f}", (tf, 1.0 - 0.1 * (f % 2)),
                        xycoords=("data", "axes fraction"), fontsize=7, ha="center", va="top",
                        color="#1f77b4" if f == tr.family else "0.4")
        a, b = nm.get(tr.ill, str(tr.ill)), nm.get(tr.obs, str(tr.obs))
        ax.set_title(f"{tr.why}: pulse at {a}, seen at {b}", fontsize=9, loc="left")
        ax.set_ylabel("STIR per bin (capture units)")
        ax.legend(fontsize=7, loc="upper right", bbox_to_anchor=(1.0, 0.82))
        ax.set_xlim(lo, hi)
        if Mt is not None:
            ax.tick_params(labelbottom=False)
            ar = fig.add_subplot(cell[1], sharex=ax)
            res = (y[win] - Mt[tr.row][win]) / (sig or 1.0)
            ar.plot(t[win], res, color="0.25", lw=0.7)
            ar.axhline(0, color="#d62728", lw=0.8)
            for v in (-3, 3):
                ar.axhline(v, color="0.5", lw=0.6, ls="--")
            ar.set_ylabel("resid./σ")
            m = float(np.max(np.abs(res))) if res.size else 3.0
            ar.set_ylim(-max(4.0, 1.1 * m), max(4.0, 1.1 * m))
            ar.set_xlabel("optical path length (m)")
        else:
            ax.set_xlabel("optical path length (m)")
    fig.suptitle(title or "most informative traces", fontsize=11)
    fig.subplots_adjust(left=0.08, right=0.98, top=1 - 0.75 / fig.get_figheight(),
                        bottom=0.55 / fig.get_figheight())
    return fig


def _symlog(ax, sig: float, top: float) -> None:
    """Symmetric-log y axis: linear within 3 sigma, decades above; ticks 0 and whole decades."""
    lin = max(3.0 * sig, 1e-300)
    ax.set_yscale("symlog", linthresh=lin)
    top = max(top, 10 * lin)
    ax.set_ylim(-2.0 * lin, 3.0 * top)
    k0, k1 = int(np.ceil(np.log10(lin))), int(np.floor(np.log10(3.0 * top)))
    step = max(1, (k1 - k0 + 1) // 6)
    ax.set_yticks([0.0] + [10.0 ** k for k in range(k0, k1 + 1, step)])
