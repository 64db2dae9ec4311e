"""f-k (Stolt) migration of a confocal scan: Lindell, Wetzstein & O'Toole, SIGGRAPH 2019 (fk.m).

When to use: a confocal scan on a regular square grid of a planar wall, rectified (t = 0 at the
wall); robust to glossy and retroreflective objects, about as fast as LCT.

Equation (wave-based NLOS, the exploding-reflector model): the field psi(x, y, z = 0, t) on the
wall, with t the one-way time, is migrated to psi(x, y, z, t = 0) by the Stolt map in the
Fourier domain

    Psi(kx, ky, kz) = [c |kz| / sqrt(kx^2 + ky^2 + kz^2)] Phi(kx, ky, f = c sqrt(kx^2 + ky^2 + kz^2)),

and the volume is |psi|^2. We follow fk.m step by step: (1) radiometric correction and square
root, psi = sqrt(tau * z^2) with z = linspace(0, 1, M); (2) zero-pad to (2M, 2N, 2N) and FFT;
(3) element-wise Stolt interpolation, linear along the frequency axis, at
f = sqrt(((N range) / (M width 4))^2 (kx^2 + ky^2) + kz^2), keeping kz > 0 and multiplying
by the element-wise Jacobian |kz| / max(f, 1e-6) (y-tal 0.20 divides by the *maximum* of f
instead, and takes |tau z| instead of sqrt(tau z^2): its depths then drift); (4) inverse FFT,
|.|^2, crop. ``width`` is the half width of the scan, ``range`` = M x bin (path length). Depth
of bin k: z = (k + 1/2) w/2.

Memory: one complex (2M, 2N, 2N) spectrum in the working precision plus the output; the Stolt
step works in slabs of ky. Neglects: what the exploding-reflector model neglects (occlusion,
the 1/r falloff beyond the radiometric correction, non-confocal paths).
"""
from __future__ import annotations

import time

import numpy as np
import scipy.fft as sfft

from .confocal import prepare
from .relay import Relay
from .settings import VolumeSettings
from .volume import Volume

__all__ = ["fk", "stolt"]


def stolt(spec: np.ndarray, a: float, slab: int = 16) -> np.ndarray:
    """Stolt-interpolate a centred (fftshifted) spectrum ``spec[kz, ky, kx]`` of shape
    (2M, 2N, 2N) in place of a new array: out(kz) = spec(f) |kz| / max(f, 1e-6) for kz > 0, with
    f = sqrt(a (kx^2 + ky^2) + kz^2) in the normalised units kz/M, ky/N, kx/N."""
    M2, N2, _ = spec.shape
    M, N = M2 // 2, N2 // 2
    out = np.zeros_like(spec)
    kz = (np.arange(M + 1, M2) - M) / M                      # kz > 0 rows
    kx = (np.arange(N2) - N) / N
    rdt = spec.real.dtype
    for j0 in range(0, N2, slab):
        j1 = min(j0 + slab, N2)
        ky = (np.arange(j0, j1) - N) / N
        lat = a * (ky[:, None] ** 2 + kx[None, :] ** 2)      # (nb, 2N)
        f = np.sqrt(lat[None] + kz[:, None, None] ** 2)       # (M-1, nb, 2N)
        pos = f * M + M
        i0 = np.floor(pos).astype(np.int64)
        fr = (pos - i0).astype(rdt)
        ok = i0 + 1 <= M2 - 1
        edge = np.isclose(pos, M2 - 1)
        i0c = np.minimum(i0, M2 - 2)
        blk = spec[:, j0:j1, :]
        lo = np.take_along_axis(blk, i0c, axis=0)
        hi = np.take_along_axis(blk, i0c + 1, axis=0)
        val = lo * (1 - fr) + hi * fr
        val = np.where(ok | edge, val, 0)
        jac = (np.abs(kz)[:, None, None] / np.maximum(f, 1e-6)).astype(rdt)
        out[M + 1:, j0:j1, :] = val * jac
    return out


def fk(relay: Relay, settings: VolumeSettings | None = None) -> Volume:
    """Reconstruct the hidden volume of a confocal relay by f-k migration (fk.m).

    Returns a Volume over depths z = (k + 1/2) w / 2 and the wall grid (x, y)."""
    st = (settings or VolumeSettings()).validate()
    t0 = time.perf_counter()
    data, cg, w, gate = prepare(relay, st)
    N, M = data.shape[0], data.shape[2]
    cdt = np.complex64 if st.dtype == "float32" else np.complex128
    rdt = np.float32 if st.dtype == "float32" else np.float64
    t_rng = M * w
    width = cg.half_width
    gz = np.linspace(0.0, 1.0, M).astype(rdt)
    psi = np.sqrt(np.maximum(data, 0) * gz[None, None, :] ** 2)       # (1) fk.m: sqrt(data z^2)
    del data
    pad = np.zeros((2 * M, 2 * N, 2 * N), dtype=cdt)                  # (2) pad (t, y, x)
    pad[:M, :N, :N] = np.moveaxis(psi, 2, 0)
    del psi
    spec = sfft.fftshift(sfft.fftn(pad, workers=st.workers, overwrite_x=True))
    del pad
    a = (N * t_rng / (M * width * 4.0)) ** 2
    spec = stolt(spec, a)                                                # (3) Stolt + Jacobian
    vol = sfft.ifftn(sfft.ifftshift(spec), workers=st.workers, overwrite_x=True)  # (4)
    del spec
    vol = (np.abs(vol[:M, :N, :N]) ** 2).astype(rdt)
    z = (np.arange(M) + 0.5) * w / 2.0
    info = {"bin_width_m": w, "gate_m": gate, "dtype": st.dtype,
            "wall_time_s": time.perf_counter() - t0,
            "grid": f"{N}x{N} lateral, {M} depths of {w / 2:.4g} m"}
    return Volume(np.ascontiguousarray(vol), cg.x, cg.y, z, cg.frame, "fk", info)
