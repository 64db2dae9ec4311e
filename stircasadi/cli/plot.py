"""``stircasadi plot``: the pictures of a capture, an estimate, or both; shared with ``run``.

    stircasadi plot CAPTURE.h5 [ESTIMATE.json] [--out DIR] [--renderer auto|pyvista|matplotlib]

* ``profiles.png`` (needs a capture): the most informative traces (``viz.informative_traces``)
  with the model — the joint fit's own prediction in ``run``; with an estimate here, the estimate
  rendered by the forward model through the capture's impulse response
  (``stircasadi.apps.render``) — and the whitened residuals;
* ``scene.png`` (needs an estimate, or a capture with a truth group): the estimated patches with
  their estimated normals and sizes over the truth (``viz.render_scene_png``).

A picture that fails is reported in one line and skipped: it never costs another picture or a
result file.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..errors import StircasadiError
from ..progress import get_logger
from . import args as A

__all__ = ["add_parsers", "cmd_plot", "make_pictures", "PICTURES"]

log = get_logger(__name__)
PICTURES = ("scene.png", "profiles.png")


def model_from_fit(result, capture):
    """The joint fit's model STIR on the capture's layout (None when there is no joint fit)."""
    fit = getattr(result, "fit", None)
    if fit is None or capture.stir is None:
        return None
    m = fit.nlp.model
    y = m.simulate(np.asarray(fit.solution.x)[:m.n_x])
    return y if y.shape == capture.stir.shape else None


def model_from_estimate(d: dict, capture):
    """The estimate rendered by the forward model on the capture's grid, ids and impulse
    response (``stircasadi.apps.render``), laid out as the capture's STIR; None when it cannot be
    rendered (the reason is logged)."""
    from ..apps.belief import SceneBelief
    from ..apps.render import RenderSettings, render
    from ..irf import from_samples
    from ..sensor import Sensor

    if capture.stir is None:
        return None
    try:
        belief = SceneBelief.from_estimate(d, allow_unreliable=True)
        sensor = Sensor(irf=from_samples(capture.irf, capture.grid.bin_width)) if capture.irf is not None \
            else Sensor()
        r = render(belief, grid=capture.grid, sensor=sensor, settings=RenderSettings(with_std=False))
    except StircasadiError as exc:
        lines = str(exc).splitlines()
        log.warning("no model curve on the profiles: " + " ".join(x.strip() for x in lines[:2])
                    + (f" (and {len(lines) - 2} more)" if len(lines) > 2 else ""))
        return None
    ri = {int(i): k for k, i in enumerate(r.ill_ids)}
    ro = {int(j): k for k, j in enumerate(r.obs_ids)}
    out = np.zeros_like(capture.stir)
    for a, i in enumerate(capture.ill_ids()):
        for b, j in enumerate(capture.obs_ids()):
            if int(i) in ri and int(j) in ro:
                out[a, b] = r.stir[ri[int(i)], ro[int(j)]]
    return out


def make_pictures(folder: Path, capture=None, estimate: dict | None = None, truth: dict | None = None,
                  model=None, model_label: str = "model", names: dict | None = None, label: str = "",
                  renderer: str = "auto") -> dict:
    """Write scene.png and profiles.png into ``folder`` where the inputs allow; returns
    {file name: (path or None, seconds, note)}. No failure propagates."""
    from ..viz import profiles_figure, render_scene_png, save_figure

    out = {}
    if estimate is not None or truth is not None:
        t = time.perf_counter()
        try:
            what = "estimate over truth" if estimate is not None and truth is not None else (
                "estimate" if estimate is not None else "truth")
            src = None if capture is None or capture.source_xyz is None else capture.source_xyz
            if estimate is not None and estimate.get("frame") == "source-origin" and truth is None:
                src = None
            path, used = render_scene_png(folder / "scene.png", estimate, truth, names, source=src,
                                          title=f"{label}: {what}".strip(": "), backend=renderer)
            out["scene.png"] = (path, time.perf_counter() - t, f"drawn with {used}")
        except Exception as exc:  # noqa: BLE001 -- a picture never costs a result
            out["scene.png"] = (None, time.perf_counter() - t, f"skipped: {type(exc).__name__}: {exc}")
    if capture is not None:
        t = time.perf_counter()
        try:
            sigma = ((estimate or {}).get("noise") or {}).get("sigma")
            fig = profiles_figure(capture, model=model, sigma=sigma, names=names, model_label=model_label,
                                  title=f"{label}: most informative traces".strip(": ")
                                  + ("" if model is not None else " (no model)"))
            out["profiles.png"] = (save_figure(fig, folder / "profiles.png"), time.perf_counter() - t, "")
        except Exception as exc:  # noqa: BLE001
            out["profiles.png"] = (None, time.perf_counter() - t, f"skipped: {type(exc).__name__}: {exc}")
    for name, (path, _, note) in out.items():
        if path is None:
            log.warning(f"{name} {note}")
    return out


def _classify(files) -> tuple:
    cap = est = None
    for f in files:
        kind = A.kind_of(f)
        if kind == "unknown":
            raise StircasadiError(f"{f} is neither a Capture (HDF5) nor an estimate.json (JSON); "
                                  "give one of each at most.")
        if (cap if kind == "capture" else est) is not None:
            raise StircasadiError(f"two {kind} files given ({cap if kind == 'capture' else est}, {f}); "
                                  "give at most one capture and one estimate.")
        if kind == "capture":
            cap = f
        else:
            est = f
    return cap, est


def cmd_plot(args) -> int:
    import json

    from ..capture import Capture
    from ..io import check_output
    from ..report import match
    from ..viz import patch_names

    if len(args.files) > 2:
        raise StircasadiError(f"plot takes a capture, an estimate, or one of each; got {len(args.files)} files.")
    cap_path, est_path = _classify(args.files)
    folder = check_output(args.out or args.files[0].parent, what="picture", folder=True)
    if folder.exists():
        for name in PICTURES:
            check_output(folder / name, inputs=args.files, what="picture")
    t0 = time.perf_counter()
    cap = Capture.read(cap_path) if cap_path else None
    d = None
    if est_path:
        try:
            d = json.loads(est_path.read_text())
        except (OSError, ValueError) as exc:
            raise StircasadiError(f"{est_path} is not readable JSON ({exc}).") from None
        if not isinstance(d, dict) or d.get("format") not in (None, "stircasadi.estimate") \
                or not isinstance(d.get("patches"), list):
            raise StircasadiError(f"{est_path} is not an estimate.json (no 'patches' list; format "
                                  f"{d.get('format') if isinstance(d, dict) else None!r}).")
    truth = cap.truth if cap is not None else None
    if cap is not None and d is None and truth is None and cap.stir is None and cap.traces is None:
        raise StircasadiError("nothing to draw.")
    names = None
    if d is not None:
        names = patch_names(d, None, match(d, truth) if truth is not None else None)
    model = None if (cap is None or d is None or args.no_model) else model_from_estimate(d, cap)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StircasadiError(f"cannot create the folder {folder}: {exc.strerror or exc}.") from None
    label = (cap_path or est_path).stem
    pics = make_pictures(folder, cap, d, truth, model, "estimate rendered by the forward model",
                         names, label, args.renderer)
    for name, (path, sec, note) in pics.items():
        print(f"{name}: " + (f"wrote {path} ({sec:.2f} s{', ' + note if note else ''})" if path else note))
    if not pics:
        raise StircasadiError("nothing to draw: give a capture (traces) and/or an estimate.")
    print(f"done in {time.perf_counter() - t0:.2f} s")
    return 0 if all(p for p, _, _ in pics.values()) else 2


def add_parsers(sub) -> list:
    p = sub.add_parser("plot", formatter_class=A.Formatter,
                       help="draw a capture's most informative traces and/or an estimate's scene",
                       description=__doc__.split("\n\n")[1] if __doc__ else None)
    p.add_argument("files", nargs="+", type=A.input_file, metavar="FILE",
                   help="a Capture (.h5), an estimate.json, or one of each")
    p.add_argument("--out", default=None, type=Path,
                   help="folder for scene.png and profiles.png (default: the folder of the first file)")
    p.add_argument("--renderer", choices=["auto", "pyvista", "matplotlib"], default="auto",
                   help="3-D renderer of scene.png: pyvista when installed (pip install 'stircasadi[3d]'), "
                        "else matplotlib")
    p.add_argument("--no-model", action="store_true",
                   help="do not render the estimate's model over the traces")
    p.set_defaults(func=cmd_plot)
    return [p]
