"""``ptu`` and ``phu``: PicoQuant TCSPC recordings (read with the ``ptufile`` package).

PTU, T3 image: one trace per pixel (= illumination point); one channel -> confocal pairs (k, k);
several channels -> full STIR, channel = observed patch. A T3 PTU without an image: the
histogram of every channel, STIR (1, n_channels, n_bins). PHU: curve k = observed k, STIR
(1, n_curves, n_bins). ``bin_width = tcspc_resolution * c``; bin 0 starts at the sync
(``start = 0``; calibrate the offset with ``calibration.time_zero``).

Neglects: PTU T2 mode (no sync, no histogram), channel-to-channel skew.
"""
from __future__ import annotations

import math

import numpy as np

from ...capture import Capture
from ...constants import C
from ...errors import ImportFormatError
from .registry import Format, register
from .validate import check_values, fail, grid as make_grid, make_capture


def _ptufile():
    try:
        import ptufile
    except ImportError as exc:  # pragma: no cover - dependency declared
        raise ImportFormatError("reading PTU/PHU needs the 'ptufile' package: pip install ptufile") from exc
    return ptufile


def capture_from_histograms(path, hist, resolution_s: float, fmt: str, image: bool = False,
                            legs_included: bool = True, provenance: dict | None = None) -> Capture:
    """Histogram counts -> Capture (shared by the PTU and PHU readers; testable without files).

    ``hist`` is ``(n_channels, n_bins)`` or, with ``image=True``, ``(n_pixels, n_channels, n_bins)``.
    """
    h = check_values(path, "histogram", hist, counts=True)
    try:
        res = float(resolution_s)
    except (TypeError, ValueError):
        raise fail(path, f"TCSPC resolution must be a number of seconds; got {resolution_s!r}.") from None
    if not (math.isfinite(res) and 0 < res < 1e-6):
        raise fail(path, f"TCSPC resolution must be in (0, 1 us) seconds; got {resolution_s!r}.")
    grid = make_grid(path, 0.0, res * C, h.shape[-1])
    prov = {"bin_width_ps": res * 1e12, **(provenance or {})}
    if image:
        if h.ndim != 3:
            raise fail(path, f"image histogram must be (pixels, channels, bins); got {h.shape}.")
        if h.shape[1] == 1:
            n = h.shape[0]
            return make_capture(path, fmt, grid=grid, traces=h[:, 0], pairs=np.stack([np.arange(n)] * 2, 1),
                            legs_included=legs_included, noise={"model": "poisson"}, provenance=prov)
        return make_capture(path, fmt, grid=grid, stir=h, legs_included=legs_included,
                        noise={"model": "poisson"}, provenance=prov)
    if h.ndim != 2:
        raise fail(path, f"histograms must be (channels, bins); got {h.shape}.")
    return make_capture(path, fmt, grid=grid, stir=h[None], legs_included=legs_included,
                    noise={"model": "poisson"}, provenance=prov)


def read_ptu(path, legs_included: bool = True) -> Capture:
    ptufile = _ptufile()
    try:
        f = ptufile.PtuFile(path)
    except Exception as exc:  # PqFileError, OSError, struct errors on corrupt files
        raise fail(path, f"not a readable PicoQuant PTU file ({type(exc).__name__}: {exc}).") from exc
    with f:
        try:
            if not f.is_t3:
                raise fail(path, "PTU file is T2 mode (no sync, no histogram); only T3 files hold "
                                  "time-of-flight histograms.")
            res = f.tcspc_resolution
            ident = {"ptu_record_type": str(f.record_type), "ptu_guid": str(f.guid),
                     "date_recorded": str(f.datetime)}
            if f.is_image:
                im = np.asarray(f.decode_image())  # (T, Y, X, C, H)
                if im.ndim != 5:
                    raise fail(path, f"PTU image has dims {f.dims}; expected T, Y, X, C, H.")
                im = im.sum(axis=0)
                y, x, c, nb = im.shape
                return capture_from_histograms(path, im.reshape(y * x, c, nb), res, "ptu", image=True,
                                               legs_included=legs_included,
                                               provenance={**ident, "scan_shape": [y, x]})
            h = np.asarray(f.decode_histogram())
        except ImportFormatError:
            raise
        except Exception as exc:
            raise fail(path, f"PTU records could not be decoded ({type(exc).__name__}: {exc}).") from exc
    return capture_from_histograms(path, h, res, "ptu", legs_included=legs_included, provenance=ident)


def read_phu(path, legs_included: bool = True) -> Capture:
    ptufile = _ptufile()
    try:
        f = ptufile.PhuFile(path)
    except Exception as exc:
        raise fail(path, f"not a readable PicoQuant PHU file ({type(exc).__name__}: {exc}).") from exc
    with f:
        try:
            hists = [np.asarray(h) for h in f.histograms()]
            res = list(f.histogram_resolutions)
        except Exception as exc:
            raise fail(path, f"PHU histograms could not be decoded ({type(exc).__name__}: {exc}).") from exc
    return phu_to_capture(path, hists, res, legs_included)


def phu_to_capture(path, hists, resolutions, legs_included: bool = True) -> Capture:
    """PHU curves (list of 1-D counts) and their resolutions (s) -> Capture."""
    if len(hists) == 0:
        raise fail(path, "PHU file holds no histogram.")
    lens = {np.asarray(h).shape for h in hists}
    if len(lens) != 1 or len(next(iter(lens))) != 1:
        raise fail(path, f"PHU curves must be 1-D of one length to form a STIR; got shapes {sorted(lens)}.")
    if len(resolutions) != len(hists) or len({float(r) for r in resolutions}) != 1:
        raise fail(path, f"PHU curves must share one resolution; got {list(resolutions)} s.")
    return capture_from_histograms(path, np.stack(hists), resolutions[0], "phu",
                                   legs_included=legs_included)


register(Format("ptu", "PicoQuant PTU (T3 histograms / images)", read_ptu,
                lambda p: p.suffix.lower() == ".ptu"))
register(Format("phu", "PicoQuant PHU histograms", read_phu, lambda p: p.suffix.lower() == ".phu"))
