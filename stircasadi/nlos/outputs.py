"""Files of a relay-wall reconstruction: maps (NPZ), a mesh (PLY via trimesh), pictures, JSON.

``write_outputs(est, folder)`` writes ``maps.npz`` (depth, albedo, mask, their std, grid,
frame, and the volumetric initialiser's maps), ``surface.ply`` (the depth map's nodes inside the
mask as a triangle mesh, albedo as vertex grey level), ``maps.png`` (depth, albedo, depth std
and the volumetric initialiser side by side), ``view3d.png`` and ``estimate.json``. Every file
is written atomically (``stircasadi.io``); an unwritable folder is an ``OutputError``.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..errors import OutputError
from ..io import atomic_path, atomic_write_text

__all__ = ["write_outputs", "surface_mesh"]


def surface_mesh(points: np.ndarray, mask: np.ndarray, albedo: np.ndarray | None = None):
    """Triangle mesh (trimesh) of a (ny, nx, 3) node grid, cells whose 4 corners are in ``mask``."""
    import trimesh

    ny, nx = mask.shape
    idx = np.arange(ny * nx).reshape(ny, nx)
    faces = []
    for iy in range(ny - 1):
        for ix in range(nx - 1):
            q = [idx[iy, ix], idx[iy, ix + 1], idx[iy + 1, ix + 1], idx[iy + 1, ix]]
            if all(mask.ravel()[k] for k in q):
                faces += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    colors = None
    if albedo is not None:
        a = np.clip(albedo.ravel() / max(float(np.max(albedo)), 1e-12), 0, 1)
        g = (255 * a).astype(np.uint8)
        colors = np.stack([g, g, g, np.full_like(g, 255)], axis=1)
    return trimesh.Trimesh(points.reshape(-1, 3), np.array(faces, int).reshape(-1, 3),
                           vertex_colors=colors, process=False)


def write_outputs(est, folder) -> dict:
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"Cannot create the output folder {folder}: {exc}. Choose a writable folder.") from exc
    if not folder.is_dir():
        raise OutputError(f"The output path {folder} is not a folder.")
    from .pictures import maps_figure, view3d_figure

    files = {}
    s, m = est.surface, est.maps
    arrays = {"init_depth": m.depth, "init_albedo": m.albedo, "init_mask": m.mask, "init_x": m.x,
              "init_y": m.y, "frame": np.vstack(est.relay.frame)}
    if s is not None:
        arrays.update({"depth": s.depth, "depth_std": s.depth_std, "albedo": s.albedo,
                       "albedo_std": s.albedo_std, "normals": s.normals, "normal_std": s.normal_std,
                       "mask": s.mask, "x": s.grid.x, "y": s.grid.y, "points": s.points()})
        pts, mask, alb = s.points(), s.mask, s.albedo
    else:
        pts, mask, alb = m.points(), m.mask, m.albedo
    with atomic_path(folder / "maps.npz") as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
    files["maps"] = "maps.npz"
    mesh = surface_mesh(pts, mask, alb)
    with atomic_path(folder / "surface.ply") as tmp:
        mesh.export(str(tmp), file_type="ply")
    files["mesh"] = "surface.ply"
    for name, fn in (("maps.png", maps_figure), ("view3d.png", view3d_figure)):
        fig = fn(est)
        with atomic_path(folder / name) as tmp:
            fig.savefig(str(tmp), dpi=110, format="png")
        import matplotlib.pyplot as plt
        plt.close(fig)
        files[name.split(".")[0]] = name
    est.files = files
    atomic_write_text(folder / "estimate.json", json.dumps(est.to_json_dict(), indent=1))
    files["estimate"] = "estimate.json"
    return files
