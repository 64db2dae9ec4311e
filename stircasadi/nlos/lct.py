"""Confocal light-cone transform (LCT): O'Toole, Lindell & Wetzstein, Nature 555, 338 (2018).

When to use: a confocal scan on a regular square grid of a planar wall, rectified (t = 0 at the
wall). Fast (three FFTs of a (2M, 2N, 2N) volume) and the usual first look at a hidden scene.

Equation. A confocal transient of a hidden albedo volume rho(x, y, z) is

    tau(x', y', t) = iiint rho(x, y, z) / r^4 delta(2 r - t) dx dy dz,
    r = sqrt((x' - x)^2 + (y' - y)^2 + z^2),

and with u = (t / 2)^2 and v = z^2 it becomes a shift-invariant 3-D convolution

    R_t{ t^4 tau }(x', y', u) = h * R_z{ rho }(x', y', u),   h(x, y, u) = delta(x^2 + y^2 - u),

(R_t, R_z resample t -> u and z -> v with the Jacobian 1 / sqrt(u)). We follow the published
steps: (1) scale the data by t^4 (diffuse) or t^2 (retroreflective); (2) resample t -> t^2
(the sparse operator averaging M sub-samples per bin, weighted 1/sqrt(u)); (3) pad to
(2M, 2N, 2N) and filter with the Wiener inverse conj(H) / (|H|^2 + 1/snr) of the kernel h;
(4) resample back with the transposed operator and clamp at 0. Depth of bin k: z = (k + 1/2) w/2.

Neglects: occlusion within the hidden scene, non-Lambertian/retroreflective mixtures, the
cosine terms (the transform assumes surfaces facing the wall), the IRF (no deconvolution of
the sensor's jitter). Precision: float32 FFTs by default (measured against float64 in the tests).
"""
from __future__ import annotations

import time

import numpy as np
import scipy.fft as sfft
import scipy.sparse as sp

from .confocal import prepare
from .relay import Relay
from .settings import VolumeSettings
from .volume import Volume

__all__ = ["lct", "resampling_operator", "lct_kernel"]


def resampling_operator(M: int) -> sp.csr_matrix:
    """(M, M) operator from the t axis to the u = t^2 axis (O'Toole et al. 2018): u-bin j
    averages the M fine samples x = jM+1..(j+1)M of tau(ceil(sqrt(x))) / sqrt(x). Its
    transpose maps u back to t."""
    x = np.arange(1, M * M + 1, dtype=np.float64)
    rows = (x - 1) // M
    cols = np.ceil(np.sqrt(x)).astype(np.int64) - 1
    vals = 1.0 / np.sqrt(x) / M
    return sp.csr_matrix((vals, (rows.astype(np.int64), cols)), shape=(M, M))


def lct_kernel(N: int, M: int, slope: float, dtype=np.float32) -> np.ndarray:
    """The LCT point spread function on the padded (2M, 2N, 2N) grid (u, y, x), normalised to
    unit energy and centred at the origin (circularly shifted): the cone
    |(4 slope)^2 (x^2 + y^2) - u| minimal along u, x, y in [-1, 1], u in [0, 2]."""
    x = np.linspace(-1.0, 1.0, 2 * N)
    r2 = (4.0 * slope) ** 2 * (x[None, :] ** 2 + x[:, None] ** 2)
    # the u sample nearest to r2 on u = linspace(0, 2, 2M); columns beyond u = 2 stay empty
    k = np.rint(r2 * (2 * M - 1) / 2.0).astype(np.int64)
    inside = k <= 2 * M - 1
    psf = np.zeros((2 * M, 2 * N, 2 * N), dtype=dtype)
    iy, ix = np.nonzero(inside)
    psf[k[inside], iy, ix] = 1.0
    psf /= psf[:, N, N].sum()
    psf /= np.linalg.norm(psf.ravel())
    return np.roll(psf, (N, N), axis=(1, 2))


def lct(relay: Relay, settings: VolumeSettings | None = None, backprojection: bool = False) -> Volume:
    """Reconstruct the hidden volume of a confocal relay by the light-cone transform.

    Parameters
    ----------
    relay : a confocal ``Relay`` on a square wall grid (``stircasadi.nlos.relay.from_capture``).
    settings : ``VolumeSettings`` (bin_factor, gate_m, t_max, diffuse, snr, dtype, workers).
    backprojection : use conj(H) instead of the Wiener inverse (the LCT's backprojection).

    Returns
    -------
    Volume with ``vol[iz, iy, ix]`` over depths z = (k + 1/2) w / 2 and the wall grid (x, y).
    """
    st = (settings or VolumeSettings()).validate()
    t0 = time.perf_counter()
    data, cg, w, gate = prepare(relay, st)
    N, M = data.shape[0], data.shape[2]
    dt = np.float32 if st.dtype == "float32" else np.float64
    t_rng = M * w                                   # path length covered by the record
    width = cg.half_width
    # (1) radiometric scaling, t normalised to the record (the published grid_z = linspace(0,1,M))
    gz = np.linspace(0.0, 1.0, M).astype(dt)
    scale = gz ** 4 if st.diffuse else gz ** 2
    data = data * scale[None, None, :]
    # (2) resample t -> u, into the padded volume (u, y, x)
    A = resampling_operator(M).astype(dt)
    pad = np.zeros((2 * M, 2 * N, 2 * N), dtype=dt)
    pad[:M, :N, :N] = (A @ data.reshape(N * N, M).T).reshape(M, N, N)
    del data
    # (3) Wiener filter with the cone kernel
    psf = lct_kernel(N, M, width / t_rng, dt)
    F = sfft.rfftn(psf, workers=st.workers)
    del psf
    if backprojection:
        inv = np.conj(F)
    else:
        inv = np.conj(F) / (np.abs(F) ** 2 + dt(1.0 / st.snr))
    del F
    spec = sfft.rfftn(pad, workers=st.workers)
    spec *= inv
    del inv
    tvol = sfft.irfftn(spec, s=pad.shape, workers=st.workers)[:M, :N, :N]
    del spec, pad
    # (4) back to t and clamp
    vol = (A.T @ np.ascontiguousarray(tvol).reshape(M, N * N)).reshape(M, N, N)
    vol = np.maximum(vol, 0).astype(dt, copy=False)
    z = (np.arange(M) + 0.5) * w / 2.0
    info = {"bin_width_m": w, "gate_m": gate, "snr": st.snr, "diffuse": st.diffuse,
            "dtype": st.dtype, "wall_time_s": time.perf_counter() - t0,
            "grid": f"{N}x{N} lateral, {M} depths of {w / 2:.4g} m"}
    return Volume(vol, cg.x, cg.y, z, cg.frame, "lct-bp" if backprojection else "lct", info)
