"""Real or simulated relay-wall scans end to end: ``estimate_capture(capture, method=...)``.

When to use: the library call behind ``stircasadi estimate --method lct|fk|bp|surface``. It
builds the relay description, runs the volumetric reconstruction (LCT or f-k for a regular
confocal scan, filtered backprojection otherwise), and with ``method="surface"`` fits the
hidden surface initialised from it. The result lists every surface node (or depth-map column)
as a hidden patch of estimate.json schema v2 (docs/estimate-json.md) and writes maps, a mesh
and pictures with ``write_outputs``.

Options (``**options``): the fields of ``VolumeSettings`` and ``SurfaceSettings``, plus
``init`` ("lct", "fk" or "bp": the initialiser of the surface fit), ``wall_step`` (keep every
k-th scan point per side of a regular confocal scan for the surface fit: its cost grows with
traces x nodes) and ``gain`` (an absolute relay gain: sets ``known_gain``). ``t_max`` (a
``VolumeSettings`` field) is the volume's window only: the surface fit and its explained-returns
check see the whole record after the gate, so a return beyond ``t_max`` still fails the check.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ReconstructionError
from .backprojection import backprojection
from .fk import fk
from .lct import lct
from .relay import Relay, from_capture
from .settings import VolumeSettings
from .surface import SurfaceResult, SurfaceSettings, fit_surface
from .volume import Maps, Volume

__all__ = ["estimate_capture", "NLOSEstimate", "METHODS", "subsample_confocal"]

METHODS = ("lct", "fk", "bp", "surface")
_VOL = {"lct": lct, "fk": fk, "bp": backprojection}


@dataclass
class NLOSEstimate:
    """What ``estimate_capture`` returns: the volume, its maps, the surface (method="surface")."""

    method: str
    relay: Relay
    volume: Volume
    maps: Maps
    surface: SurfaceResult | None = None
    stages: dict = field(default_factory=dict)
    reasons: list = field(default_factory=list)
    id_base: int = 0
    source_xyz: np.ndarray | None = None
    camera_xyz: np.ndarray | None = None
    files: dict = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return not self.reasons

    def to_json_dict(self) -> dict:
        from .report import json_dict
        return json_dict(self)

    def write_outputs(self, folder) -> dict:
        """Write maps (NPZ), mesh (PLY), pictures (PNG) and estimate.json into ``folder``."""
        from .outputs import write_outputs
        return write_outputs(self, folder)


def subsample_confocal(relay: Relay, step: int) -> Relay:
    """Every ``step``-th point per side of a regular confocal scan, summing the step x step block
    of traces it stands for (the counts of the block, so Poisson weights stay valid); the block's
    spread of scan points is the trace's ``footprint``."""
    if step <= 1:
        return relay
    from .relay import confocal_grid

    cg = confocal_grid(relay)
    n = len(cg.x) // step
    if n < 2:
        raise ReconstructionError(f"wall_step={step} leaves fewer than 2 scan points per side.")
    d = cg.data[: n * step, : n * step].astype(np.float64)
    d = d.reshape(n, step, n, step, -1).sum(axis=(1, 3))
    xs = cg.x[: n * step].reshape(n, step).mean(axis=1)
    ys = cg.y[: n * step].reshape(n, step).mean(axis=1)
    c, u, v, w = relay.frame
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    P = c[None] + xx.reshape(-1, 1) * u + yy.reshape(-1, 1) * v
    nrm = np.tile(w, (n * n, 1))
    # the block's scan points spread the trace's delays: their variance along u and v (a
    # discrete uniform of step points at the scan's spacing), modelled like a node's cell
    var = [((a[-1] - a[0]) / (len(a) - 1)) ** 2 * (step ** 2 - 1) / 12.0 for a in (cg.x, cg.y)]
    return Relay(d.reshape(n * n, -1), relay.grid, P, P.copy(), nrm, nrm.copy(), np.zeros(n * n),
                 np.full(n * n, float(np.mean(relay.gain))), None if relay.sigma is None else
                 float(np.mean(relay.sigma)) * step, relay.irf, True, relay.frame, dict(relay.meta),
                 np.tile(var, (n * n, 1)))


def _is_regular_confocal(relay: Relay) -> bool:
    from .relay import confocal_grid
    try:
        confocal_grid(relay)
        return True
    except ReconstructionError:
        return False


def estimate_capture(capture, method: str = "surface", out_dir=None, **options) -> NLOSEstimate:
    """Reconstruct the hidden scene of a relay-wall ``capture`` (never reading its ``truth``).

    Parameters
    ----------
    capture : ``stircasadi.capture.Capture`` with relay points (paired / confocal, or a full STIR
        whose visible points are given).
    method : "lct", "fk", "bp" (volumes and their maps) or "surface" (the surface fit,
        initialised by ``init``).
    out_dir : when given, ``write_outputs(out_dir)`` is called before returning.
    options : see the module docstring.

    Returns
    -------
    NLOSEstimate; ``to_json_dict()`` is estimate.json schema v2.
    """
    if method not in METHODS:
        raise ReconstructionError(f"method must be one of {METHODS}; got {method!r}.")
    opts = dict(options)
    init = opts.pop("init", None)
    step = int(opts.pop("wall_step", 1))
    gain = opts.pop("gain", None)
    vkeys = set(VolumeSettings.__dataclass_fields__)
    skeys = set(SurfaceSettings.__dataclass_fields__)
    bad = sorted(set(opts) - vkeys - skeys)
    if bad:
        raise ReconstructionError(f"Unknown option(s) {bad}; known: {sorted(vkeys | skeys | {'init', 'wall_step', 'gain'})}.")
    vst = VolumeSettings(**{k: v for k, v in opts.items() if k in vkeys}).validate()
    sst_kw = {k: v for k, v in opts.items() if k in skeys}
    relay = from_capture(capture)
    if gain is not None:
        relay.gain = relay.gain * float(gain)
        sst_kw.setdefault("known_gain", True)
    regular = _is_regular_confocal(relay)
    vm = method if method != "surface" else (init or ("lct" if regular else "bp"))
    if vm in ("lct", "fk") and not regular:
        raise ReconstructionError(f"method {vm!r} needs a regular confocal scan of a planar wall; this "
                                  "capture is not one. Use method='bp' (or init='bp' for the surface).")
    t0 = time.perf_counter()
    vol = _VOL[vm](relay, vst)
    t1 = time.perf_counter()
    gate = vol.info.get("gate_m")
    maps = vol.maps(z_min=max(0.5 * gate, 0.0) if gate is not None else None)
    stages = {"volume": {"method": vm, "status": "ok", "success": True, "iterations": 0,
                         "wall_time_s": t1 - t0, "grid": vol.info.get("grid"), "gate_m": gate}}
    ids = [int(np.max(capture.ill_ids())), int(np.max(capture.obs_ids()))]
    est = NLOSEstimate(method, relay, vol, maps, stages=stages, id_base=max(ids) + 1,
                       source_xyz=capture.source_xyz, camera_xyz=capture.camera_xyz)
    if method == "surface":
        sst = SurfaceSettings(**sst_kw).validate()
        rl = subsample_confocal(relay, step) if (step > 1 and regular) else relay
        if vst.bin_factor > 1:
            rl = _rebin(rl, vst.bin_factor)
        surf = fit_surface(rl, maps, sst, gate=gate)
        est.surface = surf
        stages["surface"] = {"status": "; ".join(l["status"] for l in surf.levels),
                             "success": surf.success,
                             "iterations": int(sum(s["iterations"] for l in surf.levels for s in l["solves"])),
                             "wall_time_s": surf.wall_time_s, **surf.summary()}
        est.reasons.extend(surf.reasons)
    if out_dir is not None:
        est.write_outputs(out_dir)
    return est


def _rebin(relay: Relay, f: int) -> Relay:
    from ..timegrid import TimeGrid

    T = (relay.grid.n_bins // f) * f
    tr = relay.traces[:, :T].reshape(relay.n_traces, T // f, f).sum(axis=2)
    g = TimeGrid(relay.grid.start, relay.grid.bin_width * f, T // f)
    sig = relay.sigma
    if sig is not None:
        sig = float(np.mean(sig)) * np.sqrt(f)
    return Relay(tr, g, relay.L, relay.D, relay.nL, relay.nD, relay.leg, relay.gain, sig, relay.irf,
                 relay.confocal, relay.frame, dict(relay.meta), relay.footprint)
