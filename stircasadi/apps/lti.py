"""The forward model driven by an arbitrary input: the paper's state space x[t+1] = A x + B u[t].

When to use
-----------
To simulate a scene under an illumination that is not a single impulse (several patches lit at
once with weights, delays and pulse shapes; a pseudo-random code; a modulated wave) *without*
superposing STIR rows: the reference that relighting by superposition
(``stircasadi.apps.relight``) and deconvolution (``stircasadi.apps.deconvolve``) are tested
against, and the simulator of coded-illumination twins.

Equation
--------
With integer delays (every leg rounded to whole bins, ``delay_mode="integer"``) the transport
network is the explicit shift-register state space of ``stircasadi.transport.statespace``:

    x[t + 1] = A x[t] + B u[t],      s[t] = C x[t],

where ``u[t]`` (n_illuminated,) is the energy sent toward each illuminated patch at the instant
t * bin_width and ``s[t]`` the radiance samples of the observed patches; the samples are binned
and spread by the sensor's discrete impulse response exactly as ``simulate(...,
method="statespace")`` does (``stircasadi.transport.deposit.bin_integer_samples``). The state
space carries every bounce.

What it neglects: sub-bin delays (the integer-delay model), light arriving after the last step.
This belongs in ``stircasadi.transport.statespace`` (a ``u`` argument to
``simulate_state_space``); it lives here, composed of the public pieces, until it moves.
"""
from __future__ import annotations

import numpy as np

from ..errors import IlluminationError
from ..scene import Scene
from ..sensor import Sensor
from ..timegrid import TimeGrid
from ..transport import TransportSystem, build_state_space
from ..transport.deposit import bin_integer_samples

__all__ = ["drive_state_space", "inputs_from_illumination"]


def drive_state_space(scene: Scene, grid: TimeGrid, inputs: np.ndarray, sensor: Sensor | None = None,
                      legs_included: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Responses of the observed patches to ``inputs`` (n_illuminated, n_steps) on ``grid``.

    ``inputs[i, t]`` is the energy aimed at the i-th illuminated patch (``scene.illuminated_ids``
    order) at the instant ``t * grid.bin_width``. Returns ``(y, obs_ids)`` with y of shape
    (n_observed, grid.n_bins). The grid's start must be a whole number of bins.
    """
    sensor = sensor or Sensor()
    if not grid.is_integer_aligned():
        raise IlluminationError(f"The state space samples t = n * bin_width; the grid start {grid.start} m "
                                f"must be a whole number of bins ({grid.bin_width} m).")
    system = TransportSystem.build(scene, delay_mode="integer", bin_width=grid.bin_width,
                                   legs_included=legs_included)
    u = np.asarray(inputs, float)
    if u.ndim != 2 or u.shape[0] != system.n_ill:
        raise IlluminationError(f"inputs must be (n_illuminated={system.n_ill}, n_steps); got {u.shape}.")
    if not np.all(np.isfinite(u)):
        raise IlluminationError("inputs hold NaN or inf.")
    ss = build_state_space(system)
    h, off = sensor.irf.discrete(grid.bin_width)
    s0 = int(round(grid.start / grid.bin_width))
    n_steps = max(s0 + grid.n_bins + off + 1, 1)
    A, B, C = ss.A, ss.B, ss.C
    x = np.zeros(ss.n_states)
    samples = np.zeros((system.n_obs, n_steps))
    for t in range(n_steps):
        samples[:, t] = C @ x
        x = A @ x
        if t < u.shape[1]:
            x += B @ u[:, t]
    return bin_integer_samples(samples, grid, sensor.irf), system.obs_ids


def inputs_from_illumination(ill_ids, illumination, bin_width: float, n_steps: int) -> np.ndarray:
    """The sample-instant input array (n_illuminated, n_steps) of an ``Illumination`` whose delays
    are whole bins (``u[i, m + l] = w_i p_i[l]`` with ``m = delay_i / bin_width``)."""
    rows, w, d, p = illumination.resolve(ill_ids)
    u = np.zeros((len(ill_ids), n_steps))
    m = d / bin_width
    if np.any(np.abs(m - np.rint(m)) > 1e-9):
        raise IlluminationError("The state space needs delays that are whole bins; got "
                                f"{(d / bin_width).tolist()} bins.")
    for r, wi, mi, pi in zip(rows, w, np.rint(m).astype(int), p):
        seg = pi[: max(n_steps - mi, 0)]
        u[r, mi:mi + len(seg)] += wi * seg
    return u
