"""Drivers against the pty emulators: known values through a real tty, unit conversion."""
from __future__ import annotations

import numpy as np
import pytest

from acq_helpers import GRID, N_OBS, N_PATCH, drivers, synthetic_row
from stircasadi.acquisition.emulators import EmulatedRig
from stircasadi.acquisition.serialio import Port, SerialSettings
from stircasadi.constants import C
from stircasadi.errors import AcquisitionSettingsError, InstrumentError


@pytest.fixture(params=["counter", "tektronix", "lecroy"])
def rig(request):
    with EmulatedRig(synthetic_row, N_PATCH, N_OBS, GRID, detector=request.param, seed=3,
                     **({"gain": 0.5, "sync_rate_hz": 1e8} if request.param == "counter"
                        else {"volts_per_unit": 0.2})) as r:
        yield r


def test_port_is_a_real_tty(rig):
    assert rig.scan.port.startswith("/dev/pts/") or rig.scan.port.startswith("/dev/tty")


def test_aim_and_read_known_rows(rig):
    with drivers(rig) as (scan, det):
        assert scan.n_patches == N_PATCH
        g = det.grid()
        # time axis converted to metres of path: the emulator's grid comes back exactly
        assert g.n_bins == GRID.n_bins
        assert g.bin_width == pytest.approx(GRID.bin_width, rel=1e-6)
        assert g.start == pytest.approx(GRID.start, abs=1e-6)
        for i in range(N_PATCH):
            scan.aim(i)
            shots = 20000 if rig.kind == "counter" else 1
            row = det.acquire(shots)
            if rig.kind == "counter":
                expect = shots * 0.5 * synthetic_row(i)
                # Poisson: every bin within 5 sigma (+1 for tiny means)
                assert np.all(np.abs(row - expect) <= 5 * np.sqrt(expect) + 1)
                assert row.sum() == pytest.approx(expect.sum(), rel=0.01)
            else:
                expect = 0.2 * synthetic_row(i)
                lsb = 1.2 * 0.2 * synthetic_row(N_PATCH - 1).max() / 32000
                np.testing.assert_allclose(row, expect, atol=lsb)  # 16-bit quantisation only


def test_scope_grid_conversion_seconds_to_metres():
    from stircasadi.acquisition.scope import tek_waveform
    pre = {"BYT_NR": 1, "BN_FMT": "RP", "BYT_OR": "MSB", "NR_PT": 4, "XUNIT": "S", "YUNIT": "V",
           "XINCR": 1e-12, "XZERO": 2e-9, "PT_OFF": 1.0, "YMULT": 0.5, "YOFF": 10.0, "YZERO": 1.0}
    wf = tek_waveform(pre, bytes([10, 12, 14, 255]))
    np.testing.assert_allclose(wf.volts, [1.0, 2.0, 3.0, 123.5])
    g = wf.grid()
    # sample 0 at XZERO - PT_OFF*XINCR = 1.999 ns is the centre of bin 0
    assert g.start == pytest.approx((2e-9 - 1e-12 - 0.5e-12) * C)
    assert g.bin_width == pytest.approx(1e-12 * C)


def test_xonxoff_refused_and_settings_validated():
    with pytest.raises(AcquisitionSettingsError, match="XON/XOFF"):
        SerialSettings(port="/dev/null", xonxoff=True).validate()
    with pytest.raises(AcquisitionSettingsError, match="baudrate"):
        SerialSettings(port="/dev/null", baudrate=12345).validate()
    with pytest.raises(AcquisitionSettingsError, match="port"):
        SerialSettings().validate()


def test_timeout_grows_with_record_length():
    s = SerialSettings(port="x", baudrate=115200, timeout_s=1.0)
    assert s.timeout_for(0) == 1.0
    assert s.timeout_for(115200) == pytest.approx(1.0 + 20.0)  # 2x the wire time of 10 bits/byte


def test_missing_port_names_device():
    with pytest.raises(InstrumentError, match="counter.*cannot open port '/nonexistent/tty'"):
        Port(SerialSettings(port="/nonexistent/tty"), device="counter").open()
