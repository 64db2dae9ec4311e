"""Wire-format parsers: known answers and fuzzed input (never a crash, never a wrong array)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stircasadi.acquisition.counter import decode_histogram
from stircasadi.acquisition.protocol import check_line, decode_block, encode_block
from stircasadi.acquisition.scope import (lecroy_encode, lecroy_waveform, parse_wfmoutpre,
                                          tek_preamble_text, tek_waveform)
from stircasadi.errors import InstrumentError

FUZZ = settings(max_examples=150, deadline=None)


def test_block_known_answer():
    assert encode_block(b"hello") == b"#15hello"
    assert decode_block(b"#15hello\n") == b"hello"
    assert decode_block(encode_block(bytes(range(256)) * 50)) == bytes(range(256)) * 50
    with pytest.raises(InstrumentError, match="truncated"):
        decode_block(b"#210abc")
    with pytest.raises(InstrumentError, match="indefinite"):
        decode_block(b"#0abc\n")


@FUZZ
@given(st.binary(max_size=64))
def test_fuzz_block_roundtrip_and_garbage(data):
    assert decode_block(encode_block(data)) == data
    try:
        out = decode_block(data)
    except InstrumentError:
        return
    # whatever decodes must be exactly what its header announced
    assert data.lstrip(b" \r\n").startswith(b"#")
    n = int(data.lstrip(b" \r\n")[1:2])
    assert len(out) == int(data.lstrip(b" \r\n")[2:2 + n])


@FUZZ
@given(st.binary(max_size=40))
def test_fuzz_line(raw):
    try:
        s = check_line(raw)
    except InstrumentError as exc:
        assert "garbage" in str(exc)
        return
    assert all(0x20 <= ord(c) <= 0x7E for c in s)


GOOD = {"BYT_NR": 2, "BIT_NR": 16, "ENCDG": "BIN", "BN_FMT": "RI", "BYT_OR": "MSB", "NR_PT": 3,
        "WFID": "Ch1; x", "PT_FMT": "Y", "XUNIT": "s", "XINCR": 1e-12, "XZERO": 0.0, "PT_OFF": 0,
        "YUNIT": "V", "YMULT": 1e-3, "YOFF": 0.0, "YZERO": 0.0}


def test_tek_known_answer():
    pre = parse_wfmoutpre(tek_preamble_text(GOOD))
    assert pre["WFID"] == "Ch1; x"
    wf = tek_waveform(pre, np.array([1, -2, 300], ">i2").tobytes())
    np.testing.assert_allclose(wf.volts, [1e-3, -2e-3, 0.3])
    with pytest.raises(InstrumentError, match="NR_PT=3 x BYT_NR=2"):
        tek_waveform(pre, b"\0" * 5)
    with pytest.raises(InstrumentError, match="YUNIT 'A'"):
        tek_waveform(parse_wfmoutpre(tek_preamble_text({**GOOD, "YUNIT": "A"})), b"\0" * 6)
    with pytest.raises(InstrumentError, match="VERBOSE"):
        parse_wfmoutpre("2;16;BIN;RI;MSB;3")


@FUZZ
@given(key=st.sampled_from(sorted(GOOD)), value=st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=8), st.integers(-5, 5)),
    payload=st.binary(max_size=12))
def test_fuzz_tek(key, value, payload):
    text = tek_preamble_text({**GOOD, key: value})
    try:
        wf = tek_waveform(parse_wfmoutpre(text), payload)
    except InstrumentError:
        return
    assert np.all(np.isfinite(wf.volts)) and wf.dt_s > 0 and wf.volts.size >= 1


def test_lecroy_known_answer():
    blob = lecroy_encode(np.array([10, -20, 30]), gain=0.5, offset=1.0, hint=2e-12, hoff=-1e-9)
    wf = lecroy_waveform(blob)
    np.testing.assert_allclose(wf.volts, [4.0, -11.0, 14.0])
    assert wf.dt_s == pytest.approx(2e-12) and wf.t0_s == -1e-9
    big = lecroy_encode(np.array([1, 2]), 1.0, 0.0, 1e-12, 0.0, little=False)
    np.testing.assert_allclose(lecroy_waveform(big).volts, [1, 2])
    with pytest.raises(InstrumentError, match="HORUNIT 'HZ'"):
        lecroy_waveform(lecroy_encode(np.array([1]), 1.0, 0.0, 1e-12, 0.0, hunit="HZ"))


@FUZZ
@given(pos=st.integers(0, 360), junk=st.binary(min_size=1, max_size=8), cut=st.integers(0, 400),
       gain=st.floats(allow_nan=True, allow_infinity=True, width=32))
def test_fuzz_lecroy(pos, junk, cut, gain):
    blob = bytearray(lecroy_encode(np.arange(5), gain=gain, offset=0.0, hint=1e-12, hoff=0.0))
    blob[pos:pos + len(junk)] = junk
    blob = bytes(blob[:cut] if cut < len(blob) else blob)
    try:
        wf = lecroy_waveform(blob)
    except InstrumentError:
        return
    assert np.all(np.isfinite(wf.volts)) and wf.dt_s > 0


@FUZZ
@given(st.binary(max_size=40), st.integers(1, 10))
def test_fuzz_histogram(payload, n):
    try:
        h = decode_histogram(payload, n)
    except InstrumentError:
        return
    assert h.shape == (n,) and np.all(h >= 0)
