"""The scene picture: estimated patches, with their estimated normals and sizes, over the truth.

When to use: after an estimate (``stircasadi run``, ``stircasadi plot``, notebooks). Nothing here
computes physics; it takes the estimate.json dict and a truth dict (a Capture's ``truth`` group
or ``Scene.truth_dict()``) and draws

* every true patch as its square (side sqrt(area)) facing its normal — visible ones blue, hidden
  ones orange — with its normal as a thin arrow;
* every estimated patch in the truth's frame (``report.alignment``: a source-origin estimate is
  rotated onto the truth by Procrustes about the source) as a square of its *estimated* area
  (or hidden extent) facing its *estimated* normal, with that normal as an arrow — visible ones
  green, hidden ones purple; a number the data could not identify is drawn as a marker (no area:
  a diamond; no normal: no arrow);
* the source (red star) and the camera (black triangle, when not at the source), patch names
  for small scenes, a legend, a scale bar and axes in metres.

``scene_figure`` draws with matplotlib (always available, headless); ``render_scene_png`` uses
pyvista when it is installed (the ``[3d]`` extra) and falls back to matplotlib when pyvista is
missing or fails, so a picture never costs a result. Neglects: occlusion between drawn patches
beyond matplotlib's painter's order.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .common import ESTIMATE_COLOURS, TRUTH_COLOURS, new_figure, save_figure

__all__ = ["SceneDrawing", "Layer", "scene_drawing", "scene_figure", "render_scene_png"]

_NICE = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0)
_MAX_LABELS = 12


@dataclass
class Layer:
    """One legend entry: squares (n, 4, 3), normal arrows (origins, vectors), markers (m, 3)."""

    label: str
    colour: str
    squares: np.ndarray
    arrow_from: np.ndarray
    arrow_vec: np.ndarray
    markers: np.ndarray
    alpha: float = 0.45
    marker: str = "D"


@dataclass
class SceneDrawing:
    """Everything a renderer draws, in the truth's frame (metres); see ``scene_drawing``."""

    layers: list
    source: np.ndarray | None
    camera: np.ndarray | None
    labels: list = field(default_factory=list)       # (position, text, colour)
    scale: float = 0.1                                # scale bar length, metres
    lo: np.ndarray = field(default_factory=lambda: np.zeros(3))
    hi: np.ndarray = field(default_factory=lambda: np.ones(3))
    title: str = ""
    notes: list = field(default_factory=list)


def _squares(centres, normals, sides) -> np.ndarray:
    """(n, 4, 3) corners of squares of side ``sides`` facing ``normals`` at ``centres``."""
    from ..radiometry import perpendicular

    out = []
    for c, n, s in zip(centres, normals, sides):
        n = np.asarray(n, float) / np.linalg.norm(n)
        t = perpendicular(n)
        b = np.cross(n, t)
        h = 0.5 * s
        out.append([c + h * (sx * t + sy * b) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    return np.array(out, float).reshape(-1, 4, 3)


def _arr(x, n=3):
    from ..report import vec

    return vec(x, n)


def _estimate_patches(estimate: dict, truth: dict | None):
    """Positions, normals (truth frame), sides (NaN: not identified), visible, ids, source, camera."""
    from ..report import alignment

    pats = estimate.get("patches") or []
    Q, s, st = (np.eye(3), np.zeros(3), np.zeros(3))
    if truth is not None and truth.get("positions") is not None:
        Q, s, st = alignment(estimate, truth)
    else:
        s = _arr(estimate.get("source_xyz"))
        s = np.zeros(3) if not np.isfinite(s).all() else s
        st = s
    P = np.array([_arr(p.get("position")) for p in pats]).reshape(-1, 3)
    N = np.array([_arr(p.get("normal")) for p in pats]).reshape(-1, 3)
    P = (P - s) @ Q + st
    N = N @ Q
    side = []
    for p in pats:
        a, e = p.get("area"), p.get("extent")
        side.append(math.sqrt(a) if a is not None and a > 0 else (float(e) if e else np.nan))
    vis = np.array([bool(p.get("visible", True)) for p in pats])
    ids = [int(p["id"]) for p in pats]

    def moved(key):
        v = _arr(estimate.get(key))
        return (v - s) @ Q + st if np.isfinite(v).all() else None
    return P, N, np.array(side), vis, ids, moved("source_xyz"), moved("camera_xyz")


def scene_drawing(estimate: dict | None = None, truth: dict | None = None, names: dict | None = None,
                  source=None, camera=None, title: str | None = None) -> SceneDrawing:
    """What to draw (see the module docstring).

    estimate : estimate.json dict (schema v2) or None (truth only).
    truth : {positions, normals, areas[, visible]} in the scene's frame, or None (estimate only).
    names : {estimated patch id: label} (``common.patch_names``); default the estimate's names.
    source, camera : their true positions (default: the estimate's, moved into the truth's frame).
    """
    if estimate is None and truth is None:
        raise ValueError("scene_drawing needs an estimate, a truth, or both.")
    layers, pts, labels, notes = [], [], [], []
    if truth is not None and truth.get("positions") is not None:
        T = np.asarray(truth["positions"], float).reshape(-1, 3)
        Tn = np.asarray(truth.get("normals", np.tile([0, 0, -1.0], (len(T), 1))), float).reshape(-1, 3)
        Ta = np.asarray(truth.get("areas", np.full(len(T), 1e-4)), float).reshape(-1)
        tv = np.asarray(truth.get("visible", np.ones(len(T), bool)), bool).reshape(-1)
        pts.append(T)
        for mask, colour, what in ((tv, TRUTH_COLOURS[0], "visible"), (~tv, TRUTH_COLOURS[1], "hidden")):
            if mask.any():
                layers.append(Layer(f"truth: {int(mask.sum())} {what}", colour,
                                    _squares(T[mask], Tn[mask], np.sqrt(Ta[mask])), T[mask], Tn[mask],
                                    np.zeros((0, 3)), alpha=0.35))
    src, cam = source, camera
    if estimate is not None and estimate.get("patches"):
        P, N, side, vis, ids, s_est, c_est = _estimate_patches(estimate, truth)
        src = s_est if src is None else src
        cam = c_est if cam is None else cam
        ok = np.isfinite(P).all(axis=1)
        pts.append(P[ok])
        hasn = np.isfinite(N).all(axis=1)
        sq = ok & hasn & np.isfinite(side)
        for mask, colour, what in ((vis, ESTIMATE_COLOURS[0], "visible"), (~vis, ESTIMATE_COLOURS[1], "hidden")):
            m = mask & ok
            if not m.any():
                continue
            mark = m & ~sq
            lab = f"estimate: {int(m.sum())} {what}"
            layers.append(Layer(lab, colour, _squares(P[m & sq], N[m & sq], side[m & sq]), P[m & hasn],
                                N[m & hasn], P[mark], alpha=0.55))
        if (~ok).any():
            notes.append(f"{int((~ok).sum())} estimated patch(es) without a position (not drawn)")
        if len(ids) <= _MAX_LABELS:
            for k in np.flatnonzero(ok):
                nm = (names or {}).get(ids[k]) or estimate["patches"][k].get("name") or str(ids[k])
                labels.append((P[k], str(nm), ESTIMATE_COLOURS[0] if vis[k] else ESTIMATE_COLOURS[1]))
    src = None if src is None else np.asarray(src, float)
    cam = None if cam is None else np.asarray(cam, float)
    for v in (src, cam):
        if v is not None:
            pts.append(v[None])
    allp = np.vstack([p for p in pts if len(p)]) if pts else np.zeros((1, 3))
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    ext = float(np.max(hi - lo)) or 1.0
    L = 0.12 * ext
    for ly in layers:
        ly.arrow_vec = ly.arrow_vec * L
    scale = max([x for x in _NICE if x <= 0.35 * ext] or [_NICE[0]])
    if cam is not None and src is not None and np.linalg.norm(cam - src) < 1e-9:
        cam = None
    return SceneDrawing(layers, src, cam, labels, scale, lo, hi,
                        title or ("estimate over truth" if estimate is not None and truth is not None
                                  else "estimate" if estimate is not None else "scene"), notes)


def _view(d: SceneDrawing):
    """(elev, azim) with y up: from behind and above the source, steeper for flat (y = const) scenes."""
    ext = d.hi - d.lo
    flat = ext[1] < 0.05 * max(float(ext.max()), 1e-12)
    return (-80.0, 0.0) if flat else (22.0, -120.0)


def _rgba(colour, alpha):
    from matplotlib.colors import to_rgba

    return to_rgba(colour, alpha)


def _scale_text(L: float) -> str:
    return f"{L * 100:g} cm" if L < 1 else f"{L:g} m"


def scene_figure(estimate: dict | None = None, truth: dict | None = None, names: dict | None = None,
                 source=None, camera=None, title: str | None = None, fig=None, drawing=None):
    """The scene picture as a matplotlib ``Figure`` (pass ``fig=plt.figure()`` in a notebook)."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch as PatchArtist
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    d = drawing or scene_drawing(estimate, truth, names, source, camera, title)
    fig = new_figure(fig, (10.0, 6.5))
    ax = fig.add_subplot(projection="3d")
    handles = []
    for ly in d.layers:
        est = ly.label.startswith("estimate")
        if len(ly.squares):  # truth: a wide pale halo; estimate: a sharp outline on top of it
            pc = Poly3DCollection(ly.squares, linewidths=1.8 if est else (5.0 if len(ly.squares) <= 20 else 1.5))
            pc.set_facecolor(_rgba(ly.colour, 0.15 if est else ly.alpha))
            pc.set_edgecolor(_rgba(ly.colour, 1.0 if est else 0.6))
            ax.add_collection3d(pc)
        if len(ly.arrow_from):
            a, v = ly.arrow_from, ly.arrow_vec
            ax.quiver(a[:, 0], a[:, 1], a[:, 2], v[:, 0], v[:, 1], v[:, 2], color=ly.colour,
                      linewidth=1.8 if est else 1.0, arrow_length_ratio=0.25,
                      linestyle="-" if est else "--")
        if len(ly.markers):
            ax.scatter(*ly.markers.T, marker=ly.marker, s=45 if len(ly.markers) <= 20 else 14, color=ly.colour,
                       edgecolor="k", linewidths=0.8 if len(ly.markers) <= 20 else 0.3, depthshade=False)
        handles.append(PatchArtist(facecolor=ly.colour, edgecolor=ly.colour, alpha=min(1.0, ly.alpha + 0.3),
                                   label=ly.label))
    if d.source is not None:
        ax.scatter(*d.source, marker="*", s=220, color="red", edgecolor="k", depthshade=False)
        ax.text(*d.source, "  source", color="red", fontsize=8)
        handles.append(Line2D([], [], marker="*", color="red", ls="", ms=12, label="source (pulsed laser)"))
    if d.camera is not None:
        ax.scatter(*d.camera, marker="^", s=90, color="k", depthshade=False)
        handles.append(Line2D([], [], marker="^", color="k", ls="", ms=8, label="camera"))
    if any(len(ly.markers) for ly in d.layers):
        handles.append(Line2D([], [], marker="D", color="0.4", mec="k", ls="", label="◆ size not identified"))
    kinds = {ly.label.split(":")[0] for ly in d.layers}
    if any(len(ly.arrow_from) for ly in d.layers if ly.label.startswith("estimate")):
        handles.append(Line2D([], [], color="0.3", lw=1.8, label="normal, estimated"))
    if "truth" in kinds:
        handles.append(Line2D([], [], color="0.3", lw=1.0, ls="--", label="normal, true"))
    for pos, text, colour in d.labels:
        ax.text(*pos, f" {text}", color=colour, fontsize=8)
    # scale bar along x at the lowest corner of the box
    ext = d.hi - d.lo
    pad = 0.08 * max(float(ext.max()), 1e-9)
    lo, hi = d.lo - pad, d.hi + pad
    p0 = np.array([lo[0] + pad, lo[1], lo[2]])
    ax.plot([p0[0], p0[0] + d.scale], [p0[1]] * 2, [p0[2]] * 2, color="k", lw=3)
    ax.text(p0[0], p0[1], p0[2], f"{_scale_text(d.scale)}\n", color="k", fontsize=9)
    handles.append(Line2D([], [], color="k", lw=3, label=f"scale bar: {_scale_text(d.scale)}"))
    ctr, half = 0.5 * (lo + hi), 0.5 * float((hi - lo).max())
    ax.set_xlim(ctr[0] - half, ctr[0] + half)
    ax.set_ylim(ctr[1] - half, ctr[1] + half)
    ax.set_zlim(ctr[2] - half, ctr[2] + half)
    ax.set_box_aspect((1, 1, 1), zoom=1.05)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    elev, azim = _view(d)
    ax.view_init(elev=elev, azim=azim, vertical_axis="y")
    ax.set_title(d.title + ("\n" + "; ".join(d.notes) if d.notes else ""), fontsize=10)
    fig.legend(handles=handles, loc="center left", bbox_to_anchor=(0.76, 0.5), fontsize=8, framealpha=0.9)
    fig.subplots_adjust(left=0.0, right=0.78, top=0.93, bottom=0.05)
    return fig


def render_scene_png(path, estimate: dict | None = None, truth: dict | None = None,
                     names: dict | None = None, source=None, camera=None, title: str | None = None,
                     backend: str = "auto") -> tuple:
    """Write the scene picture to ``path`` (PNG, atomically); returns (path, backend used).

    backend : ``"auto"`` (pyvista when installed, else matplotlib), ``"pyvista"`` or
        ``"matplotlib"``. A pyvista failure (missing, no OpenGL) falls back to matplotlib with
        a logged warning; a matplotlib failure raises.
    """
    from ..progress import get_logger

    if backend not in ("auto", "pyvista", "matplotlib"):
        raise ValueError(f"backend must be 'auto', 'pyvista' or 'matplotlib'; got {backend!r}.")
    d = scene_drawing(estimate, truth, names, source, camera, title)
    if backend in ("auto", "pyvista"):
        try:
            from .scene_vtk import render_pyvista

            return render_pyvista(d, path), "pyvista"
        except ModuleNotFoundError as exc:
            if backend == "pyvista" or exc.name not in ("pyvista", "vtk"):
                get_logger(__name__).warning(f"3-D picture with pyvista unavailable ({exc}); drawing "
                                             "it with matplotlib (pip install 'stircasadi[3d]')")
        except Exception as exc:  # noqa: BLE001 -- any pyvista/VTK failure: draw with matplotlib
            get_logger(__name__).warning(f"3-D picture with pyvista failed ({type(exc).__name__}: "
                                         f"{exc}); drawing it with matplotlib instead")
    return save_figure(scene_figure(drawing=d), path), "matplotlib"
