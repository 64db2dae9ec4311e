"""Pictures of a study: accuracy against time with the Pareto front, accuracy against noise next
to the Cramér-Rao bound, coverage of the error bars, the cost and change of each effect.

When to use
-----------
``draw_all(results, folder)`` draws what the results support (the runner calls it); each
``plot_*`` function takes a ``StudyResults`` and returns a matplotlib Figure, for notebooks.

What the pictures show
----------------------
* **Accuracy vs time**: one point per design point (median time, RMS error over repetitions),
  one panel per varied factor coloured by its level; the Pareto front (no other point of the
  same scene is both faster and more accurate) is the black line, one per problem / scene.
* **Accuracy vs noise**: the RMS error over repetitions and the RMS of the std the estimator
  reports (its Cramér-Rao bound at the estimate), visible and hidden patches apart (a missed
  hidden patch has no number: its point is absent). An efficient, honest estimator puts the two
  curves on top of each other; error above the bound means the bars are too small.
* **Coverage**: the fraction of |err|/std <= k against k, beside the Gaussian promise
  erf(k/sqrt 2) and its binomial band (alpha = 1e-3) for the number of values; numbers reported
  without a std count as outside every k.
* **Effects**: simulation time with the effect forced, relative to the automatic choice,
  against the largest change of the STIR in noise std.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.ticker import NullFormatter

from ..progress import get_logger
from .results import as_text

log = get_logger(__name__)

__all__ = ["draw_all", "pareto_front", "plot_accuracy_vs_time", "plot_accuracy_vs_noise",
           "plot_coverage", "plot_effects"]

_LABELS = {"err_position_m": "RMS position error (m)", "err_position_m_hidden": "RMS hidden position error (m)",
           "err_albedo": "RMS albedo error", "err_normal_deg": "RMS normal error (deg)",
           "estimate_s": "estimate time (s)", "wall_s": "cell wall time (s)", "simulate_s": "simulation time (s)"}


def _plt():
    import matplotlib.pyplot as plt

    return plt


def pareto_front(x, y) -> np.ndarray:
    """Boolean mask of the points no other point beats in both x and y (both minimised)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    mask = np.zeros(len(x), bool)
    idx = np.flatnonzero(ok)
    order = idx[np.lexsort((y[idx], x[idx]))]
    best = math.inf
    for i in order:
        if y[i] < best:
            mask[i] = True
            best = y[i]
    return mask


def _design(res):
    return [c for c in res.design_columns() if c not in ("label",)] or res.design_columns()


def _points(res, acc: str, tcol: str):
    import pandas as pd

    c = res.cells[res.cells["status"] == "ok"].copy()
    design = res.design_columns()
    c[acc] = pd.to_numeric(c[acc], errors="coerce")
    c[tcol] = pd.to_numeric(c[tcol], errors="coerce")
    if not design:
        return c.assign(_acc=c[acc], _t=c[tcol]), design
    g = c.groupby(design, dropna=False, sort=False)
    pts = g.agg(_t=(tcol, "median"), _acc=(acc, lambda s: float(np.sqrt(np.nanmean(np.square(s))))
                                               if np.isfinite(s).any() else np.nan)).reset_index()
    return pts, design


def plot_accuracy_vs_time(res, acc: str = "err_position_m", tcol: str = "estimate_s"):
    """Accuracy against time per varied factor, Pareto front marked."""
    plt = _plt()
    pts, design = _points(res, acc, tcol)
    design = [d for d in design if d != "label"] or design
    n = max(len(design), 1)
    cols = min(n, 3)
    rows = int(math.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(5.0 * cols, 4.0 * rows), squeeze=False)
    # one Pareto front per scene: accuracies of different scenes are not comparable
    scene_cols = [c for c in ("problem", "scene", "label") if c in design]
    scene_key = (pts[scene_cols].apply(lambda r: " / ".join(map(str, r)), axis=1) if scene_cols
                 else pts["_t"].map(lambda _: "all"))
    fronts = []
    for key in dict.fromkeys(scene_key):
        sub = pts[scene_key == key]
        f = pareto_front(sub["_t"], sub["_acc"])
        fx, fy = sub["_t"][f].to_numpy(), sub["_acc"][f].to_numpy()
        o = np.argsort(fx)
        fronts.append((fx[o], fy[o]))
    for ax, fac in zip(axes.flat, design or [None]):
        if fac is None:
            ax.scatter(pts["_t"], pts["_acc"], s=18)
        else:
            text = as_text(pts[fac])
            levels = list(dict.fromkeys(text))
            cmap = plt.get_cmap("tab10" if len(levels) <= 10 else "viridis")
            for i, lev in enumerate(levels):
                sel = text == lev
                ax.scatter(pts["_t"][sel], pts["_acc"][sel], s=18, color=cmap(i / max(len(levels) - 1, 1)
                                                                            if len(levels) > 10 else i),
                           label=lev[:24])
            ax.set_title(f"by {fac}")
            ax.legend(fontsize=7, loc="best")
        for fx, fy in fronts:
            ax.plot(fx, fy, "k-", lw=1.2, drawstyle="steps-post", label="_Pareto")
            ax.scatter(fx, fy, s=60, facecolors="none", edgecolors="k", lw=1.0)
        ax.set_xscale("log")
        lo, hi = ax.get_xlim()
        if hi > 10 * lo:  # minor labels only where the axis spans less than a decade
            ax.xaxis.set_minor_formatter(NullFormatter())
        if (pts["_acc"] > 0).any():
            ax.set_yscale("log")
        ax.set_xlabel(_LABELS.get(tcol, tcol) + " (median)")
        ax.set_ylabel(_LABELS.get(acc, acc))
        ax.grid(alpha=0.3, which="both")
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    fig.suptitle(f"{res.study.get('name')}: {_LABELS.get(acc, acc)} vs time, median over repetitions "
                 f"(Pareto front per scene: black, circled)", fontsize=10)
    fig.tight_layout()
    return fig


def plot_accuracy_vs_noise(res, noise_col: str = "noise", quantities=("position", "albedo")):
    """RMS error over repetitions and the RMS reported std (the CRB at the estimate) vs noise."""
    import pandas as pd

    plt = _plt()
    c = res.cells[res.cells["status"] == "ok"]
    num = res.numbers
    num = num[(num["cell"].isin(c["cell"])) & num["kind"].isin(["component", "scalar"]) & ~num["given"]]
    merged = num.merge(c[["cell", noise_col] + [d for d in res.design_columns() if d != noise_col]],
                       on="cell")
    groups = [d for d in res.design_columns() if d not in (noise_col, "repetition", "seed")]
    fig, axes = plt.subplots(1, len(quantities), figsize=(5.2 * len(quantities), 4.0), squeeze=False)
    for ax, q in zip(axes.flat, quantities):
        mq = merged[merged["quantity"] == q].copy()
        mq[noise_col] = pd.to_numeric(mq[noise_col], errors="coerce")
        keys = mq.groupby(groups, dropna=False, sort=False) if groups else [("all", mq)]
        for i, (key, sub) in enumerate(keys):
            lab = key if isinstance(key, str) else ", ".join(map(str, np.atleast_1d(key)))
            color = f"C{i % 10}"
            for vis, marker, kind in ((True, "o", "visible"), (False, "s", "hidden")):
                part = sub[sub["visible"] == vis]
                if not len(part):
                    continue
                g = part.groupby(noise_col)
                rms_err = g["err"].apply(lambda e: float(np.sqrt(np.mean(np.square(e)))))
                rms_std = g["std"].apply(lambda s: float(np.sqrt(np.nanmean(np.square(s))))
                                         if s.notna().any() else np.nan)
                ax.plot(rms_err.index, rms_err.values, marker=marker, ls="-", color=color,
                        label=f"{lab}, {kind}: RMS error")
                ax.plot(rms_std.index, rms_std.values, marker=marker, ls="--", mfc="none", color=color,
                        label=f"{lab}, {kind}: reported std")
        if noise_col == "noise":
            ax.set_xscale("log")
        if ax.has_data():
            ax.set_yscale("log")
        ax.set_xlabel("noise std relative to the peak" if noise_col == "noise" else "peak SNR (dB)")
        ax.set_ylabel(f"{q} error ({'m' if q == 'position' else '1'})")
        ax.set_title(f"{q}: error vs reported std")
        ax.grid(alpha=0.3, which="both")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
        else:
            ax.text(0.5, 0.5, f"no {q} reported", transform=ax.transAxes, ha="center")
    fig.suptitle(f"{res.study.get('name')}: accuracy vs noise beside the Cramér-Rao bound", fontsize=10)
    fig.tight_layout()
    return fig


def plot_coverage(res, quantities=None, alpha: float = 1e-3):
    """Fraction of |err|/std <= k vs k per quantity, beside the Gaussian promise and its band."""
    from scipy.stats import binom

    plt = _plt()
    ok = res.cells.loc[res.cells["status"] == "ok", "cell"]
    num = res.numbers
    num = num[num["cell"].isin(ok) & num["kind"].isin(["component", "scalar"]) & ~num["given"]]
    qs = quantities or [q for q in ("position", "normal", "albedo", "albedo_area", "area", "specular", "exponent")
                        if (num["quantity"] == q).any()]
    k = np.linspace(0, 5, 101)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.0))
    ax = axes[0]
    nominal = np.array([math.erf(x / math.sqrt(2)) for x in k])
    ax.plot(k, nominal, "k-", lw=2, label="Gaussian promise erf(k/√2)")
    for q in qs:
        z = num.loc[num["quantity"] == q, "z"].to_numpy(float)
        if not z.size:
            continue
        frac = np.array([(z <= x).mean() for x in k])
        line, = ax.plot(k, frac, label=f"{q} (n={z.size}, no std {np.mean(~np.isfinite(z)):.0%})")
        n = z.size
        lo = binom.ppf(alpha / 2, n, nominal) / n
        hi = binom.ppf(1 - alpha / 2, n, nominal) / n
        ax.fill_between(k, lo, hi, color=line.get_color(), alpha=0.12)
    ax.set_xlabel("k (sigma)")
    ax.set_ylabel("fraction with |err|/std <= k")
    ax.set_title("coverage (bands: binomial, alpha=1e-3)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax = axes[1]
    zf = num["z"].to_numpy(float)
    zf = zf[np.isfinite(zf)]
    if zf.size:
        bins = np.linspace(0, max(5.0, min(float(np.percentile(zf, 99)), 50.0)), 41)
        ax.hist(np.clip(zf, 0, bins[-1]), bins=bins, density=True, alpha=0.6, label=f"|err|/std (n={zf.size})")
        x = np.linspace(0, bins[-1], 200)
        ax.plot(x, 2 * np.exp(-x ** 2 / 2) / math.sqrt(2 * math.pi), "k-", label="half-normal")
    ax.set_xlabel("|err|/std (clipped at the right edge)")
    ax.set_ylabel("density")
    ax.set_title("|err|/std of the numbers with a std")
    ax.legend(fontsize=7)
    fig.suptitle(f"{res.study.get('name')}: coverage of the reported error bars", fontsize=10)
    fig.tight_layout()
    return fig


def plot_effects(res):
    """Cost (time ratio forced / automatic) against change (max STIR change in noise std)."""
    import pandas as pd

    plt = _plt()
    c = res.cells[(res.cells["status"].isin(["ok", "refused", "crashed"])) &
                  (res.cells["effect_state"] != "auto")].copy()
    for col in ("simulate_s", "sim_s_auto", "stir_change_sigma", "stir_change_rel"):
        c[col] = pd.to_numeric(c.get(col), errors="coerce")
    c["ratio"] = c["simulate_s"] / c["sim_s_auto"]
    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    markers = {"on": "^", "off": "v"}
    effects = list(dict.fromkeys(c["effect"]))
    cmap = plt.get_cmap("tab10")
    for i, eff in enumerate(effects):
        for st, mk in markers.items():
            sel = (c["effect"] == eff) & (c["effect_state"] == st)
            y = c.loc[sel, "stir_change_sigma"].fillna(c.loc[sel, "stir_change_rel"] / 1e-4)
            ax.scatter(c.loc[sel, "ratio"], np.maximum(y, 1e-6), marker=mk, color=cmap(i), s=30,
                       label=f"{eff} {st}")
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    ax.text(ax.get_xlim()[0] if ax.get_xlim()[0] > 0 else 0.5, 1.1, " 1 noise std", fontsize=7)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("simulation time, forced / automatic")
    ax.set_ylabel("max |STIR change| / noise std (floor 1e-6)")
    ax.set_title(f"{res.study.get('name')}: what forcing an effect costs and changes")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    return fig


def draw_all(res, folder) -> list[Path]:
    """Draw every picture the results support into ``folder``; returns the files."""
    plt = _plt()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    made = []
    c = res.cells
    if not len(c) or not (c["status"] == "ok").any():
        return made
    figs = res.study.get("figures") or {}
    acc_cols = figs.get("accuracy") or ["err_position_m", "err_albedo"]
    tcol = figs.get("time", "estimate_s")

    def save(draw, name, *args):
        try:
            fig = draw(res, *args)
        except (ValueError, KeyError, TypeError) as exc:  # a picture must not lose the tables
            log.warning(f"picture {name} not drawn: {type(exc).__name__}: {exc}")
            plt.close("all")
            return
        p = folder / name
        fig.savefig(p, dpi=110)
        plt.close(fig)
        made.append(p)

    design = res.design_columns()
    if design and tcol in c.columns:
        for acc in acc_cols:
            if acc in c.columns and np.isfinite(np.asarray(c[acc], float)).any():
                save(plot_accuracy_vs_time, f"accuracy_vs_time_{acc}.png", acc, tcol)
    ok = c[c["status"] == "ok"]
    for ncol in ("noise", "snr_db"):
        if ncol in design and len(res.numbers) and ok[ncol].notna().sum() > 1:
            save(plot_accuracy_vs_noise, f"accuracy_vs_{ncol}.png", ncol)
    if len(res.numbers) and "z" in res.numbers.columns:
        save(plot_coverage, "coverage.png")
    if "effect" in c.columns and "effect_state" in c.columns and "sim_s_auto" in c.columns:
        save(plot_effects, "effects.png")
    return made
