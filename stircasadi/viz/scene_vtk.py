"""The scene picture drawn by pyvista/VTK off-screen (the optional ``[3d]`` extra).

When to use: through ``scene.render_scene_png`` (which falls back to matplotlib when this module
fails). It draws the same ``SceneDrawing`` as ``scene.scene_figure``: squares, normal arrows,
markers, names, source/camera, legend, scale bar and a grid in metres, viewed from behind the
source (along y for flat scenes). VTK's complaint about a missing X display is kept off the
terminal (no display is needed: the render window is off-screen).
"""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import numpy as np

__all__ = ["render_pyvista"]


@contextlib.contextmanager
def _c_stderr_to_devnull():
    """Silence C-level writes to standard error (VTK's X-server warnings) for the block."""
    import logging

    from ..progress import get_logger

    if get_logger().isEnabledFor(logging.DEBUG):  # -v: show what VTK says
        yield
        return
    fd = 2  # C libraries write to file descriptor 2 whatever Python's sys.stderr is
    try:
        sys.stderr.flush()
        saved = os.dup(fd)
    except (AttributeError, OSError, ValueError):  # no descriptor 2 at all
        yield
        return
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)


def _polydata(pv, squares):
    n = len(squares)
    pts = squares.reshape(-1, 3)
    faces = np.hstack([np.full((n, 1), 4), np.arange(4 * n).reshape(n, 4)]).ravel()
    return pv.PolyData(pts, faces)


def _arrows(pv, origins, vectors, thick: bool):
    """Thin arrows (one merged mesh) from ``origins`` along ``vectors``."""
    meshes = []
    for a, v in zip(origins, vectors):
        n = float(np.linalg.norm(v))
        if n > 0:
            meshes.append(pv.Arrow(start=a, direction=v / n, tip_length=0.25, tip_radius=0.09 if thick else 0.06,
                                   shaft_radius=0.03 if thick else 0.015, scale=n))
    return pv.merge(meshes) if meshes else pv.PolyData()


def _camera(d):
    """(position, focal point, view up): from behind the source, y up; along -y for flat scenes."""
    ctr = 0.5 * (d.lo + d.hi)
    ext = float(np.max(d.hi - d.lo)) or 1.0
    flat = (d.hi - d.lo)[1] < 0.05 * ext
    if flat:
        return ctr - 2.6 * ext * np.array([0.0, 1.0, 0.0]), ctr, (0.0, 0.0, 1.0)
    fwd = ctr - (d.source if d.source is not None else ctr - np.array([0, 0, 1.0]))
    fwd = fwd / (np.linalg.norm(fwd) or 1.0)
    side = np.cross(fwd, [0.0, 1.0, 0.0])
    side = side / (np.linalg.norm(side) or 1.0)
    eye = -fwd + 0.45 * np.array([0.0, 1.0, 0.0]) + 0.75 * side
    return ctr + 2.2 * ext * eye / np.linalg.norm(eye), ctr, (0.0, 1.0, 0.0)


def render_pyvista(d, path, window_size=(1200, 800)) -> Path:
    """Render the ``SceneDrawing`` ``d`` to the PNG ``path`` (written atomically)."""
    import pyvista as pv

    from ..io import atomic_path
    from .scene import _scale_text

    path = Path(path)
    ext = float(np.max(d.hi - d.lo)) or 1.0
    with _c_stderr_to_devnull():
        pl = pv.Plotter(off_screen=True, window_size=list(window_size))
        try:
            pl.set_background("white")
            legend, markers = [], False
            for ly in d.layers:
                est = ly.label.startswith("estimate")
                if len(ly.squares):
                    pl.add_mesh(_polydata(pv, ly.squares), color=ly.colour, opacity=0.3 if est else 0.55,
                                show_edges=True, edge_color=ly.colour, line_width=4 if est else 1)
                if len(ly.arrow_from):
                    pl.add_mesh(_arrows(pv, ly.arrow_from, ly.arrow_vec, thick=est), color=ly.colour)
                if len(ly.markers):
                    pl.add_points(ly.markers, color=ly.colour, point_size=16, render_points_as_spheres=True)
                    markers = True
                legend.append([ly.label, ly.colour])
            if d.source is not None:
                pl.add_mesh(pv.Sphere(radius=0.02 * ext, center=d.source), color="red")
                pl.add_point_labels([d.source], ["source"], text_color="red", font_size=14,
                                    shape=None, show_points=False, always_visible=True)
                legend.append(["source (pulsed laser)", "red"])
            if d.camera is not None:
                pl.add_mesh(pv.Cube(center=d.camera, x_length=0.03 * ext, y_length=0.03 * ext,
                                    z_length=0.03 * ext), color="black")
                legend.append(["camera", "black"])
            if d.labels:
                pl.add_point_labels(np.array([p for p, _, _ in d.labels]), [t for _, t, _ in d.labels],
                                    text_color="black", font_size=12, shape=None, show_points=False,
                                    always_visible=True)
            p0 = np.array([d.lo[0], d.lo[1], d.lo[2]]) - 0.06 * ext
            pl.add_mesh(pv.Line(p0, p0 + np.array([d.scale, 0.0, 0.0])), color="black", line_width=6)
            pl.add_point_labels([p0 + np.array([0.5 * d.scale, 0.0, 0.0])], [_scale_text(d.scale)],
                                text_color="black", font_size=14, shape=None, show_points=False,
                                always_visible=True)
            legend.append([f"scale bar: {_scale_text(d.scale)}", "black"])
            if markers:
                legend.append(["ball: size not identified", "gray"])
            legend.append(["arrows: normals (thick: estimate)", "gray"])
            pl.add_legend(legend, bcolor="white", border=True, size=(0.3, 0.024 * len(legend)),
                          loc="upper left", face="rectangle")
            pl.show_grid(xtitle="x (m)", ytitle="y (m)", ztitle="z (m)", color="gray", font_size=10)
            pl.add_text(d.title + ("\n" + "; ".join(d.notes) if d.notes else ""), font_size=11,
                        color="black", position="upper_left")
            pl.camera_position = _camera(d)
            pl.reset_camera()
            pl.camera.zoom(0.85)
            with atomic_path(path, suffix=".png") as tmp:
                pl.screenshot(str(tmp))
        finally:
            pl.close()
    return path
