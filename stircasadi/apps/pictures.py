"""Pictures of the applications: the scene's patches as a camera sees them, coloured by a value
(radiance under a new lighting or material, direct or global light), scan images of relay-wall
captures, and time profiles before/after.

Nothing here computes physics. Every function takes arrays and writes a PNG (matplotlib, Agg),
returning its path; ``ax=`` draws into an existing axis instead (notebooks).

Projection: a pinhole at the camera looking at the patches' centroid (up = +y unless the view is
along y); each patch is drawn as its square (side sqrt(area)) facing its normal, far patches
first. Neglects: occlusion between patches beyond that painter's order, perspective of colours.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["patch_image", "scan_image", "profiles", "bars"]


def _plt():
    import matplotlib.pyplot as plt  # the backend is the caller's (Agg headless, inline in notebooks)
    return plt


def _save(fig, path):
    if path is None:
        return None
    from ..io import atomic_path

    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def _finish(ax, own: bool, path):
    """Save and close a figure this module made (returning its path); else return the axis."""
    if not own:
        return ax
    import matplotlib.pyplot as plt

    fig = ax.figure
    fig.tight_layout()
    out = _save(fig, path)
    plt.close(fig)
    return out


def _squares(positions, normals, areas):
    out = []
    for c, n, a in zip(positions, normals, areas):
        n = np.asarray(n, float) / np.linalg.norm(n)
        t = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
        t /= np.linalg.norm(t)
        b = np.cross(n, t)
        h = 0.5 * math.sqrt(a)
        out.append([c + h * (sx * t + sy * b) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return np.array(out)


def patch_image(positions, normals, areas, values, camera, path=None, title: str = "",
                label: str = "radiance", log: bool = False, ids=None, ax=None, vmin=None, vmax=None):
    """The patches seen from ``camera``, coloured by ``values`` (NaN: grey, not seen)."""
    plt = _plt()
    from matplotlib.collections import PolyCollection

    P = np.asarray(positions, float)
    cam = np.asarray(camera, float)
    f = P.mean(axis=0) - cam
    f /= np.linalg.norm(f)
    up = np.array([0.0, 1.0, 0.0]) if abs(f[1]) < 0.95 else np.array([0.0, 0.0, 1.0])
    r = np.cross(f, up)
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    sq = _squares(P, normals, areas) - cam
    depth = sq @ f
    xy = np.stack([(sq @ r) / depth, (sq @ u) / depth], axis=-1)
    order = np.argsort(-depth.mean(axis=1))
    v = np.asarray(values, float)
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(5.5, 4.5))
    shown = v[np.isfinite(v)]
    if log:
        shown = shown[shown > 0]
    lo = vmin if vmin is not None else (float(shown.min()) if shown.size else 0.0)
    hi = vmax if vmax is not None else (float(shown.max()) if shown.size else 1.0)
    import matplotlib.colors as mcolors
    norm = (mcolors.LogNorm(max(lo, 1e-300), max(hi, lo * 1.0001 + 1e-300)) if log
            else mcolors.Normalize(lo, hi if hi > lo else lo + 1e-12))
    cmap = plt.get_cmap("inferno")
    colors = [cmap(norm(v[k])) if np.isfinite(v[k]) and (not log or v[k] > 0) else (0.6, 0.6, 0.6, 1.0)
              for k in order]
    ax.add_collection(PolyCollection(xy[order], facecolors=colors, edgecolors="k", linewidths=0.4))
    if ids is not None:
        for k in range(len(P)):
            ax.text(*xy[k].mean(axis=0), str(ids[k]), ha="center", va="center", fontsize=6, color="c")
    ax.set_xlim(xy[..., 0].min() - 0.02, xy[..., 0].max() + 0.02)
    ax.set_ylim(xy[..., 1].min() - 0.02, xy[..., 1].max() + 0.02)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title(title, fontsize=9)
    sm = plt.cm.ScalarMappable(norm=norm, cmap=cmap)
    ax.figure.colorbar(sm, ax=ax, label=label, shrink=0.8)
    return _finish(ax, own, path)


def scan_image(values, shape, path=None, title: str = "", label: str = "", log: bool = False, ax=None):
    """A relay-wall scan (values in scan order) as an image of ``shape`` (rows, cols)."""
    plt = _plt()
    img = np.asarray(values, float).reshape(shape)
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(4.8, 4.2))
    import matplotlib.colors as mcolors
    pos = img[img > 0]
    norm = mcolors.LogNorm(pos.min(), pos.max()) if (log and pos.size) else None
    im = ax.imshow(img, origin="lower", cmap="inferno", norm=norm)
    ax.set_title(title, fontsize=9)
    ax.figure.colorbar(im, ax=ax, label=label, shrink=0.8)
    return _finish(ax, own, path)


def profiles(t, curves: dict, path=None, title: str = "", log: bool = False, bands: dict | None = None,
             ax=None, xlabel: str = "optical path length (m)"):
    """Time profiles ``{label: y}`` against ``t`` (metres), with optional ``{label: std}`` bands."""
    plt = _plt()
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(7.5, 4.0))
    for lab, y in curves.items():
        y = np.asarray(y, float)
        line, = ax.plot(t, np.clip(y, 1e-300, None) if log else y, lw=1.1, label=lab)
        if bands and lab in bands and bands[lab] is not None:
            s = np.asarray(bands[lab], float)
            ax.fill_between(t, y - 2 * s, y + 2 * s, color=line.get_color(), alpha=0.25, lw=0)
    if log:
        ax.set_yscale("log")
        top = max(float(np.max(np.asarray(y))) for y in curves.values())
        ax.set_ylim(top * 1e-8, top * 3)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("radiance per bin")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    return _finish(ax, own, path)


def bars(ids, series: dict, path=None, title: str = "", errors: dict | None = None, ax=None,
         ylabel: str = "time-integrated radiance", log: bool = False):
    """Grouped bars per patch id: ``{label: values}`` with optional ``{label: errors}``."""
    plt = _plt()
    own = ax is None
    if own:
        fig, ax = plt.subplots(figsize=(max(5.0, 0.35 * len(ids) * len(series)), 3.8))
    x = np.arange(len(ids))
    wd = 0.8 / max(len(series), 1)
    for k, (lab, v) in enumerate(series.items()):
        e = None if not errors else errors.get(lab)
        ax.bar(x + (k - (len(series) - 1) / 2) * wd, v, wd, yerr=e, label=lab, capsize=2)
    ax.set_xticks(x, [str(i) for i in ids], fontsize=7)
    ax.set_xlabel("patch id")
    ax.set_ylabel(ylabel)
    if log:
        ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    return _finish(ax, own, path)
