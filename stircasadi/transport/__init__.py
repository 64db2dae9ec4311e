"""Forward transient transport: a scene + time grid + sensor -> ideal STIR (``Transient``).

Three independent solvers of the same delay network (``system.TransportSystem``):

* ``method="bounces"``: exact path sums up to K bounces (``bounces.py``), any sensor;
* ``method="frequency"``: the resolvent, all bounces or K (``frequency.py``), fast;
* ``method="statespace"``: the paper's explicit x[t+1] = A x + B u, y = C x with integer
  delays (``statespace.py``), small scenes only.

Only the effects a scene calls for are computed (DESIGN.md section 7): the bounce order defaults
to what the scene needs (3 with hidden patches, else 2), rays are cast only when the scene has
occluders, per-direction (glossy) nodes exist only for glossy patches, the impulse response only
when the sensor has one; noise is added later by ``Sensor.capture``. ``Transient.metadata``
lists what was applied and the energy each truncation left out.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import TimeGridError, TransportError
from ..scene import Scene
from ..sensor import Sensor
from ..timegrid import TimeGrid
from .bounces import path_sum
from .deposit import kernel_support
from .frequency import bounce_energies, frequency_solve
from .statespace import build_state_space, simulate_state_space
from .system import TransportSystem

__all__ = ["Transient", "simulate", "needed_bounces", "TransportSystem", "radiosity",
           "build_state_space", "simulate_state_space", "path_sum", "frequency_solve"]


@dataclass
class Transient:
    """An ideal (noise-free) STIR ``stir[i, j, k]`` on ``grid`` with what produced it."""

    stir: np.ndarray
    grid: TimeGrid
    ill_ids: np.ndarray
    obs_ids: np.ndarray
    metadata: dict = field(default_factory=dict)
    scene: Scene | None = None
    per_bounce: list | None = None

    def capture(self, sensor: Sensor | None = None, seed: int | None = 0, noise: bool = True):
        """Shorthand for ``sensor.capture(self, seed)``."""
        return (sensor or Sensor()).capture(self, seed=seed, noise=noise)


def needed_bounces(scene: Scene) -> int:
    """The bounce order the scene calls for: 3 when patches are hidden (third-bounce geometry),
    else 2 (second-bounce onsets give every visible distance)."""
    return 3 if scene.hidden.any() else 2


def simulate(scene: Scene, grid: TimeGrid, sensor: Sensor | None = None, method: str = "auto",
             bounces: int | str | None = None, delay_mode: str = "exact",
             legs_included: bool = True, allow_truncation: bool = False,
             per_bounce: bool = False, link_level: bool = False,
             tail_tol: float = 1e-10, out=None) -> Transient:
    """Simulate the ideal STIR of ``scene`` on ``grid`` through ``sensor``'s impulse response.

    Parameters
    ----------
    bounces : int K, ``"all"``, or None (the order the scene needs: ``needed_bounces``).
    method : ``"auto"``, ``"bounces"``, ``"frequency"`` or ``"statespace"``.
    delay_mode : ``"exact"`` (true path lengths) or ``"integer"`` (each leg rounded to bins,
        the paper's model).
    legs_included : False gives relay-wall style times without the source and camera legs.
    allow_truncation : permit a grid that starts after the first arrival or ends before the
        last path of the requested order (otherwise a ``TimeGridError`` says what grid is needed).
    out : optional array-like of the STIR's shape (``np.memmap``, h5py dataset) that the
        frequency method fills block by block, for scenes whose STIR should not sit in memory.
    """
    if not isinstance(scene, Scene):
        raise TransportError(f"simulate needs a Scene; got {type(scene).__name__}.")
    if not isinstance(grid, TimeGrid):
        raise TransportError(f"simulate needs a TimeGrid; got {type(grid).__name__}.")
    sensor = sensor or Sensor()
    irf = sensor.irf
    t0 = time.perf_counter()
    if bounces is None:
        K: int | None = needed_bounces(scene)
    elif bounces == "all":
        K = None
    elif isinstance(bounces, (int, np.integer)) and not isinstance(bounces, bool) and bounces >= 1:
        K = int(bounces)
    else:
        raise TransportError(f"bounces must be an integer >= 1, 'all' or None; got {bounces!r}.")
    if delay_mode not in ("exact", "integer"):
        raise TransportError(f"delay_mode must be 'exact' or 'integer'; got {delay_mode!r}.")
    if delay_mode == "integer" and not grid.is_integer_aligned():
        raise TimeGridError(f"delay_mode='integer' needs a grid start that is a whole number of bins; "
                            f"got start={grid.start} m with bin_width={grid.bin_width} m.")
    system = TransportSystem.build(scene, delay_mode=delay_mode, bin_width=grid.bin_width,
                                   legs_included=legs_included, link_level=link_level)
    if method == "auto":
        if K is None:
            method = "frequency"
        else:
            n_paths = system.n_ill * max(system.n_nodes, 1) ** max(K - 1, 0)
            band_ok = delay_mode == "integer" or irf.band_limited
            method = "frequency" if (n_paths > 3e7 and band_ok) else "bounces"
    if method not in ("bounces", "frequency", "statespace"):
        raise TransportError(f"method must be 'auto', 'bounces', 'frequency' or 'statespace'; got {method!r}.")
    if method == "bounces" and K is None:
        raise TransportError("method='bounces' sums a finite number of bounces; give bounces=K, or "
                             "use method='frequency' for all bounces.")
    if method == "statespace" and delay_mode != "integer":
        raise TransportError("method='statespace' is the paper's integer-delay model: pass "
                             "delay_mode='integer'.")
    _check_grid(system, grid, irf, K if K is not None else needed_bounces(scene), allow_truncation,
                delay_mode)
    meta = dict(system.metadata)
    meta.update({"method": method, "bounces": "all" if K is None else K, "delay_mode": delay_mode,
                 "irf": irf.describe(), "n_illuminated": system.n_ill, "n_observed": system.n_obs})
    parts = None
    if method == "bounces":
        res = path_sum(system, grid, irf, K, per_bounce=per_bounce)
        stir, parts = res if per_bounce else (res, None)
    elif method == "frequency":
        stir, info = frequency_solve(system, grid, irf, K, tail_tol=tail_tol, out=out)
        meta.update(info)
    else:
        if bounces is not None and K is not None:
            raise TransportError("method='statespace' carries every bounce; pass bounces='all' (or "
                                 "leave it None) and compare with the all-bounce methods.")
        ss = build_state_space(system)
        meta["n_states"] = ss.n_states
        stir = simulate_state_space(ss, system, grid, irf)
        K = None  # the state space carries every bounce
        meta["bounces"] = "all"
    if out is not None and method != "frequency":
        out[...] = stir
        stir = out
    meta.update(_energy_report(system, K, stir))
    meta["wall_time_s"] = time.perf_counter() - t0
    return Transient(stir=stir, grid=grid, ill_ids=system.ill_ids, obs_ids=system.obs_ids,
                     metadata=meta, scene=scene, per_bounce=parts)


def _check_grid(system, grid, irf, K, allow_truncation, delay_mode):
    lo_s, hi_s = kernel_support(irf, grid.bin_width, delay_mode == "integer")
    t_lo, t_hi = system.arrival_window(K)
    if not np.isfinite(t_lo):
        return
    if allow_truncation:
        return
    w = grid.bin_width
    if t_lo + lo_s < grid.start - 1e-12:
        raise TimeGridError(
            f"The grid starts at {grid.start:.4g} m but the first light arrives at {t_lo:.4g} m of "
            f"path (impulse response reaches {t_lo + lo_s:.4g} m); it would be cut off. Start the "
            f"grid at or before {math.floor((t_lo + lo_s) / w) * w:.4g} m, or pass allow_truncation=True.")
    if t_hi + hi_s > grid.end + 1e-12:
        need = int(math.ceil((t_hi + hi_s - grid.start) / w)) + 1
        raise TimeGridError(
            f"The grid ends at {grid.end:.4g} m of path but {K}-bounce light arrives until "
            f"{t_hi + hi_s:.4g} m; the STIR would be truncated silently. Use n_bins >= {need} "
            f"(bin_width {w:g} m), fewer bounces, or pass allow_truncation=True.")


def _energy_report(system, K, stir) -> dict:
    """Energies (summed over the STIR, exact at zero frequency) left out by each truncation."""
    n_max = 64 if K is None else max(K, 1)
    try:
        e, total = bounce_energies(system, n_max)
    except Exception:  # singular (I - T0): reported by the spectral radius instead
        return {}
    if total <= 0:
        return {"total_energy": 0.0}
    out = {"total_energy": float(total), "bounce_energy": [float(x) for x in e[:8]]}
    if K is not None:
        out["omitted_energy_rel"] = float(max(total - e[:K].sum(), 0.0) / total)
        in_model = e[:K].sum()
    else:
        in_model = total
    out["energy_after_grid_rel"] = float(max(in_model - stir.sum(), 0.0) / total)
    return out


def radiosity(scene: Scene) -> np.ndarray:
    """Steady-state (time-integrated) STIR of a Lambertian scene by classic radiosity.

    Written independently of the delay network: ``B = E + diag(rho/pi) G^T B`` with
    ``G[h, k] = a_h cos_h cos_k v_hk / d_hk^2`` and ``E_k = rho_k phi / (pi a_k)`` for the aimed
    patch; returns ``R[i, j]`` = radiance of observed j with the pulse at i (n_ill, n_obs).
    """
    from ..brdf import Lambertian
    from ..radiometry import cosines, form_factor

    if not all(isinstance(b, Lambertian) for b in scene.brdfs):
        raise TransportError("radiosity() handles Lambertian scenes only.")
    z, n, a = scene.positions, scene.normals, scene.areas
    vec = z[None, :, :] - z[:, None, :]
    d = scene.distances.copy()
    np.fill_diagonal(d, 1.0)
    ch, ck = cosines(vec, n[:, None, :], n[None, :, :], d)
    G = form_factor(a[:, None], ch, ck, d) * scene.patch_visibility
    rho = scene.albedos
    K = (rho[:, None] / np.pi) * G.T
    ill, obs = scene.illuminated_ids, scene.observed_ids
    E = np.zeros((scene.n_patches, len(ill)))
    E[ill, np.arange(len(ill))] = rho[ill] * scene.phi / (np.pi * a[ill])
    Bm = np.linalg.solve(np.eye(scene.n_patches) - K, E)
    return Bm[obs].T


