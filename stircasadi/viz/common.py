"""What every picture shares: figures made without pyplot, atomic PNG writes, names of patches.

Figures are ``matplotlib.figure.Figure`` objects built through the object API, so nothing here
selects or changes a backend: files are written headless (Agg) whatever the session's backend,
and in a notebook the caller passes ``fig=plt.figure()`` (or calls ``display(fig)``) to see
them inline.
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["new_figure", "save_figure", "patch_names", "TRUTH_COLOURS", "ESTIMATE_COLOURS"]

#: colours of the truth (visible, hidden) and of the estimate (visible, hidden)
TRUTH_COLOURS = ("#9db4d6", "#f0a048")
ESTIMATE_COLOURS = ("#1a9641", "#b2188b")


def new_figure(fig=None, figsize=(8.0, 5.0)):
    """``fig`` cleared for drawing, or a new headless ``Figure`` of ``figsize`` inches."""
    if fig is not None:
        fig.clf()
        return fig
    from matplotlib.figure import Figure

    return Figure(figsize=figsize)


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Write ``fig`` as a PNG atomically (temporary file + rename: never a truncated picture)."""
    from ..io import atomic_path

    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return path


def patch_names(estimate: dict | None = None, truth_names=None, matched=None) -> dict:
    """{patch id: label}: the estimate's names, replaced by the scene's own names (``truth_names``
    in truth order) where ``matched`` (truth index per estimated patch, ``report.match``) says
    which true patch an estimated one is."""
    out = {}
    for k, p in enumerate((estimate or {}).get("patches") or []):
        nm = p.get("name") or str(p.get("id"))
        if truth_names is not None and matched is not None and 0 <= matched[k] < len(truth_names) \
                and truth_names[matched[k]]:
            nm = str(truth_names[matched[k]])
        out[int(p["id"])] = str(nm)
    return out
