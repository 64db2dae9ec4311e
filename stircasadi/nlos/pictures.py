"""Pictures of a relay-wall reconstruction (matplotlib, headless-safe: figures are returned).

``maps_figure``: the volumetric initialiser's depth and albedo beside the surface fit's depth,
albedo and depth std (masked). ``view3d_figure``: the surface (or depth-map) points in 3-D
with the relay points. Neglects nothing; pictures only.

Maps are drawn as seen from the relay wall, looking into the hidden scene (``wall_view``): the
relay frame (u, v, w) is right-handed with w towards the hidden scene, so that view has v up and
u to the LEFT. A sign that faces the wall then reads as it does to someone standing at the wall;
drawn with u to the right (``imshow``'s default) it would be mirrored.
"""
from __future__ import annotations

import numpy as np

__all__ = ["maps_figure", "view3d_figure", "wall_view"]


def wall_view(ax, img, x, y, **imshow_kw):
    """Draw the map ``img[iy, ix]`` over the relay-frame coordinates ``x``, ``y`` (ascending) as
    seen from the wall: y up, x increasing to the left (see the module docstring)."""
    im = ax.imshow(img, origin="lower", extent=[x[0], x[-1], y[0], y[-1]], **imshow_kw)
    if not ax.xaxis_inverted():
        ax.invert_xaxis()
    ax.set_xlabel("x (m), seen from the wall")
    ax.set_ylabel("y (m)")
    return im


def maps_figure(est):
    import matplotlib.pyplot as plt

    s, m = est.surface, est.maps
    panels = [("init depth (m)", np.where(m.mask, m.depth, np.nan), m, "viridis"),
              ("init albedo (rel.)", m.albedo, m, "gray")]
    if s is not None:
        g = s.grid
        panels += [("surface depth (m)", np.where(s.mask, s.depth, np.nan), g, "viridis"),
                   ("surface albedo", s.albedo, g, "gray"),
                   ("depth std (mm)", np.where(s.mask, 1e3 * s.depth_std, np.nan), g, "magma")]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.2))
    for ax, (title, img, gr, cmap) in zip(np.atleast_1d(axes), panels):
        im = wall_view(ax, img, gr.x, gr.y, cmap=cmap)
        ax.set_title(title, fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046)
    fig.suptitle(f"{est.method}: {est.volume.method} initialiser" + (
        f", surface chi2/dof={s.chi2_dof:.3g}" if s is not None else ""), fontsize=10)
    fig.tight_layout()
    return fig


def view3d_figure(est):
    import matplotlib.pyplot as plt

    s = est.surface
    if s is not None:
        P, mask, col = s.points().reshape(-1, 3), s.mask.ravel(), s.albedo.ravel()
    else:
        P, mask, col = est.maps.points().reshape(-1, 3), est.maps.mask.ravel(), est.maps.albedo.ravel()
    fig = plt.figure(figsize=(5, 4.5))
    ax = fig.add_subplot(111, projection="3d")
    W = np.vstack([est.relay.L, est.relay.D])
    ax.scatter(W[:, 0], W[:, 1], W[:, 2], s=1, c="0.7", label="relay")
    ax.scatter(P[mask, 0], P[mask, 1], P[mask, 2], s=8, c=col[mask], cmap="viridis", label="hidden")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
