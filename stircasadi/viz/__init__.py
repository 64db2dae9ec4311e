"""Pictures: the scene (estimate over truth) and the most informative time profiles."""
from .common import new_figure, patch_names, save_figure
from .profiles import informative_traces, profiles_figure
from .scene import render_scene_png, scene_drawing, scene_figure

__all__ = ["new_figure", "save_figure", "patch_names", "scene_drawing", "scene_figure",
           "render_scene_png", "informative_traces", "profiles_figure"]
