"""Pictures: the scene in 3-D (pyvista, off-screen) and STIR time profiles (matplotlib).

Nothing here computes physics; functions take scenes, transients, captures or estimates and
write PNG files. Both libraries run headless (``MPLBACKEND=Agg``; pyvista ``off_screen``).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def _patch_squares(positions, normals, areas):
    """A pyvista PolyData of small squares (one per patch), facing along the normals."""
    import pyvista as pv

    pts, faces = [], []
    for k, (c, n, a) in enumerate(zip(positions, normals, areas)):
        n = np.asarray(n, float)
        if not np.all(np.isfinite(n)) or np.linalg.norm(n) == 0:
            n = np.array([0.0, 0.0, -1.0])
        n = n / np.linalg.norm(n)
        t = np.cross(n, [1.0, 0, 0]) if abs(n[0]) < 0.9 else np.cross(n, [0, 1.0, 0])
        t /= np.linalg.norm(t)
        b = np.cross(n, t)
        h = 0.5 * math.sqrt(a)
        base = len(pts)
        pts += [c + h * (sx * t + sy * b) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        faces += [4, base, base + 1, base + 2, base + 3]
    return pv.PolyData(np.array(pts), np.array(faces))


def render_scene(scene, path: str | Path, estimate_positions: np.ndarray | None = None,
                 estimate_normals: np.ndarray | None = None, title: str | None = None,
                 window_size=(900, 700)) -> Path:
    """Render the scene's patches (visible grey-blue, hidden orange), the source/camera, and
    optionally estimated patches (green) beside them; write a PNG."""
    import pyvista as pv

    path = Path(path)
    pl = pv.Plotter(off_screen=True, window_size=window_size)
    vis = scene.visible | scene.illuminable
    for mask, color in ((vis, "lightsteelblue"), (~vis, "orange")):
        if mask.any():
            pl.add_mesh(_patch_squares(scene.positions[mask], scene.normals[mask], scene.areas[mask]),
                        color=color, show_edges=True)
    if scene.occluders is not None:
        pl.add_mesh(pv.wrap(scene.occluders), color="dimgray", opacity=0.35)
    pl.add_mesh(pv.Sphere(radius=0.03, center=scene.source), color="red")
    if np.linalg.norm(scene.camera - scene.source) > 1e-9:
        pl.add_mesh(pv.Sphere(radius=0.03, center=scene.camera), color="black")
    if estimate_positions is not None:
        nrm = estimate_normals if estimate_normals is not None else scene.normals
        pl.add_mesh(_patch_squares(estimate_positions, nrm, scene.areas * 0.6), color="limegreen",
                    opacity=0.8)
    pl.add_axes()
    if title:
        pl.add_text(title, font_size=10)
    pl.camera_position = "xy"
    pl.camera.azimuth = 35
    pl.camera.elevation = 25
    pl.reset_camera()
    pl.screenshot(str(path))
    pl.close()
    return path


def plot_profiles(stir: np.ndarray, grid, path: str | Path, pairs=None, log: bool = True,
                  title: str | None = None, ids=None) -> Path:
    """Time profiles ``stir[i, j, :]`` for a few (i, j) pairs against path length (metres)."""
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    path = Path(path)
    n_i, n_j = stir.shape[:2]
    if pairs is None:
        pairs = [(0, 0)] + [(0, j) for j in range(1, min(n_j, 4))] + ([(1, 1)] if n_i > 1 else [])
    fig, ax = plt.subplots(figsize=(8, 4.5))
    t = grid.centres
    for i, j in pairs:
        y = stir[i, j]
        lab = f"pulse {ids[0][i] if ids else i} -> seen {ids[1][j] if ids else j}"
        ax.plot(t, np.clip(y, 1e-30, None) if log else y, lw=1.0, label=lab)
    if log:
        ax.set_yscale("log")
        top = float(np.max(stir)) if stir.size else 1.0
        ax.set_ylim(top * 1e-9, top * 3)
    ax.set_xlabel("optical path length (m)")
    ax.set_ylabel("radiance per bin")
    ax.set_title(title or "STIR time profiles")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
