"""Fuzzed .mat files through the relay-wall scan importers: clear ImportFormatError, never a crash."""
from __future__ import annotations

import numpy as np
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stircasadi.acquisition.importers import import_file
from stircasadi.errors import CaptureError, ImportFormatError

FUZZ = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
vals = st.sampled_from([0.0, 1.0, 7.0, -1.0, np.nan, np.inf])



def _import_checked(p, fmt):
    """Import ``p`` as ``fmt``: refused with ImportFormatError / CaptureError, or finite,
    non-negative traces / STIR."""
    try:
        cap = import_file(p, fmt)
    except (ImportFormatError, CaptureError):
        return
    data = cap.stir if cap.stir is not None else cap.traces
    assert np.all(np.isfinite(data)) and np.all(data >= 0)

@FUZZ
@given(shape=st.lists(st.integers(0, 4), min_size=1, max_size=4), v=vals,
       width=st.one_of(vals, st.just(None)))
def test_fuzz_stanford(tmp_path, shape, v, width):
    p = tmp_path / "f.mat"
    d = {"rect_data": np.full(shape, v)}
    if width is not None:
        d["width"] = width
    scipy.io.savemat(p, d)
    _import_checked(p, "stanford-lct")  # refused, or finite non-negative data


@FUZZ
@given(n=st.integers(0, 4), nt=st.integers(0, 5), v=vals, ci=st.integers(-1, 3))
def test_fuzz_ccsocr(tmp_path, n, nt, v, ci):
    p = tmp_path / "sub_Sig.mat"
    scipy.io.savemat(p, {"sub_Sig": np.full((n, nt), v)})
    scipy.io.savemat(tmp_path / "C_i.mat", {"C_i": np.full((n, 3), ci)})
    scipy.io.savemat(tmp_path / "C_d.mat", {"C_d": np.full((n, 3), ci)})
    _import_checked(p, "ccsocr")  # refused, or finite non-negative data


@FUZZ
@given(rows=st.integers(0, 6), nt=st.integers(0, 5), v=vals)
def test_fuzz_general_nlos(tmp_path, rows, nt, v):
    p = tmp_path / "data_x.mat"
    scipy.io.savemat(p, {"counts": np.full((rows, nt), v)})
    _import_checked(p, "general-nlos")  # refused, or finite non-negative data
