"""Scope protocol faults over both transports, and a VISA capture of an emulated LAN scope."""
from __future__ import annotations

import time

import numpy as np
import pytest

from acq_helpers import GRID, N_OBS, N_PATCH, drivers, synthetic_row
from stircasadi.acquisition.emulators import EmulatedRig, Fault
from stircasadi.acquisition.session import acquire
from stircasadi.capture import Capture
from stircasadi.errors import InstrumentError

pytest.importorskip("pyvisa", reason="the VISA transport needs the 'visa' extra (pyvisa, pyvisa-py)")
TRANSPORTS = ["pty", "tcp"]


def scope_rig(kind="tektronix", transport="pty", **kw):
    return EmulatedRig(synthetic_row, N_PATCH, N_OBS, GRID, detector=kind, seed=5, transport=transport,
                       volts_per_unit=0.1, noise_v=0.0, **kw)


@pytest.mark.parametrize("transport", TRANSPORTS)
@pytest.mark.parametrize("kind", ["tektronix", "lecroy"])
def test_scope_ignoring_data_source_is_caught(tmp_path, transport, kind):
    """Every CH2 waveform would be CH1's: the preamble (WFID / WAVE_SOURCE) gives it away."""
    with scope_rig(kind, transport, ignores_source=True) as rig, drivers(rig) as (scan, det):
        scan.aim(0)
        with pytest.raises(InstrumentError, match="CH1|C1") as ei:
            det.acquire(1)
        assert "2" in str(ei.value) and "when C" in str(ei.value)
        with pytest.raises(InstrumentError):
            acquire(scan, det, tmp_path / "c.h5", shots=1)
    assert not (tmp_path / "c.h5").exists()


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_corrupt_block_length_fails_in_seconds(transport):
    """``#9099999999`` then silence: refused on its header, not after hours of waiting."""
    with scope_rig("tektronix", transport, detector_faults=[Fault("badlength", "CURVE?", nth=2)]) as rig, \
            drivers(rig, timeout_s=1.0) as (scan, det):
        scan.aim(0)
        t0 = time.monotonic()
        with pytest.raises(InstrumentError, match="announces 99999999 bytes but the preamble allows "
                                                  "exactly 256"):
            det.acquire(1)
        assert time.monotonic() - t0 < 5.0


def test_corrupt_histogram_length_refused_on_header():
    from stircasadi.acquisition.counter import CounterSettings, HistogramCounter  # noqa: F401
    with EmulatedRig(synthetic_row, N_PATCH, N_OBS, GRID, detector="counter", gain=0.5, sync_rate_hz=1e8,
                     detector_faults=[Fault("badlength", "HIST?", nth=1)]) as rig, \
            drivers(rig, timeout_s=1.0) as (scan, det):
        scan.aim(0)
        with pytest.raises(InstrumentError, match="exactly 512"):
            det.acquire(10)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_dpo_style_preamble_is_kept_and_recorded(tmp_path, transport):
    out = tmp_path / "dpo.h5"
    with scope_rig("tektronix", transport, dpo_preamble=True) as rig, drivers(rig) as (scan, det):
        acquire(scan, det, out, shots=1)
    cap = Capture.read(out)
    np.testing.assert_allclose(cap.stir, 0.1 * np.stack([synthetic_row(i) for i in range(N_PATCH)]),
                               atol=1.2 * 0.1 * synthetic_row(N_PATCH - 1).max() / 32000)
    import json
    extra = json.loads(cap.provenance["detector"])["preamble_extra"]
    assert extra["DOMAIN"] == "TIME" and extra["WFMTYPE"] == "ANALOG_YT" and "CENTERFREQUENCY" in extra


def test_frequency_domain_record_refused():
    from stircasadi.acquisition.scope import parse_wfmoutpre, tek_preamble_text
    good = {"BYT_NR": 2, "BN_FMT": "RI", "BYT_OR": "MSB", "NR_PT": 3, "XUNIT": "s", "XINCR": 1e-12,
            "XZERO": 0.0, "PT_OFF": 0, "YUNIT": "V", "YMULT": 1e-3, "YOFF": 0.0, "YZERO": 0.0,
            "WFID": "Ch1, DC coupling"}
    assert parse_wfmoutpre(tek_preamble_text({**good, "DOMAIN": "TIME"}))["DOMAIN"] == "TIME"
    with pytest.raises(InstrumentError, match="DOMAIN FREQUENCY"):
        parse_wfmoutpre(tek_preamble_text({**good, "DOMAIN": "FREQUENCY"}))


@pytest.mark.parametrize("kind", ["tektronix", "lecroy"])
def test_visa_capture_of_emulated_lan_scope_equals_forward_model(tmp_path, kind):
    """``acquire --emulate three_patch --emulate-transport visa``: the scope is a loopback TCP
    socket opened as ``TCPIP0::127.0.0.1::<port>::SOCKET`` through pyvisa; the capture equals the
    forward model within the scope noise (1 mV per shot, averaged)."""
    from stircasadi.acquisition.cli import forward_source, main
    out = tmp_path / "visa.h5"
    shots = 16
    rc = main(["acquire", "--emulate", "three_patch", "--emulate-transport", "visa", "--detector", kind,
               "--out", str(out), "--shots", str(shots), "--timeout", "1", "--quiet", "--seed", "2"])
    assert rc == 0
    cap = Capture.read(out)
    *_, tr = forward_source("three_patch")
    ideal = np.asarray(tr.stir)
    expect = 0.5 / ideal.max() * ideal                     # volts_per_unit of the emulated rig
    resid = cap.stir - expect
    sigma = 1e-3 / np.sqrt(shots)
    lsb = (1.2 * 0.5 + 4e-3) / 32000
    assert abs(resid.mean()) < 5 * sigma / np.sqrt(resid.size) + lsb
    assert resid.std() == pytest.approx(np.sqrt(sigma ** 2 + lsb ** 2 / 12), rel=0.1)
    assert np.max(np.abs(resid)) < 6 * sigma + lsb
    assert "TCPIP0::127.0.0.1::" in cap.provenance["detector"]
    assert cap.provenance["emulated_transport"] == "visa"
