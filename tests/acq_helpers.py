"""Shared helpers for the acquisition tests (synthetic STIR source, rig fixtures)."""
from __future__ import annotations

import contextlib

import numpy as np

from stircasadi.acquisition.counter import CounterSettings, HistogramCounter
from stircasadi.acquisition.emulators import EmulatedRig
from stircasadi.acquisition.scan import ScanController, ScanSettings
from stircasadi.acquisition.scope import Oscilloscope, ScopeSettings
from stircasadi.acquisition.serialio import SerialSettings
from stircasadi.timegrid import TimeGrid

GRID = TimeGrid(1.0, 0.01, 128)
N_PATCH, N_OBS = 3, 2


def synthetic_row(i: int) -> np.ndarray:
    """A known STIR row: Gaussian pulses whose delays depend on (i, j)."""
    t = GRID.centres
    row = np.zeros((N_OBS, GRID.n_bins))
    for j in range(N_OBS):
        centre = 1.3 + 0.1 * i + 0.05 * j
        row[j] = (1.0 + i + j) * np.exp(-0.5 * ((t - centre) / 0.02) ** 2)
    return row


def fast(port: str, retries: int = 0, timeout_s: float = 0.3) -> SerialSettings:
    return SerialSettings(port=port, timeout_s=timeout_s, retries=retries, retry_settle_s=0.01)


@contextlib.contextmanager
def drivers(rig: EmulatedRig, retries: int = 0, timeout_s: float = 0.3):
    """Open the scan controller and the detector of an emulated rig; always closed after."""
    scan = ScanController(ScanSettings(fast(rig.scan.port, retries, timeout_s)))
    if rig.kind == "counter":
        det = HistogramCounter(CounterSettings(fast(rig.detector.port, retries, timeout_s),
                                               channels=tuple(range(N_OBS))))
    else:
        det = Oscilloscope(ScopeSettings(fast(rig.detector.port, retries, timeout_s), dialect=rig.kind,
                                         channels=tuple(range(1, N_OBS + 1))))
    try:
        scan.open()
        det.open()
        yield scan, det
    finally:
        scan.close()
        det.close()


# ------------------------------------------------------------------ a cheap rig for the CLI in a child
#: the child's scan: 12 patches, 2 observed, 64 bins (one row = 1 KiB)
CHILD_GRID = TimeGrid(1.0, 0.01, 64)
CHILD_PATCHES = 12


def child_row(i: int) -> np.ndarray:
    t = CHILD_GRID.centres
    return np.stack([(1.0 + i + j) * np.exp(-0.5 * ((t - 1.2 - 0.02 * i - 0.05 * j) / 0.02) ** 2)
                     for j in range(N_OBS)])


def child_main(argv) -> int:
    """``python tests/acq_helpers.py acquire --emulate synthetic ...``: the real ``acquire`` CLI
    (signals, lock, journal, resume) on an emulated rig backed by ``child_row``."""
    import stircasadi.acquisition.cli as cli

    cli.forward_source = lambda problem: (child_row, CHILD_PATCHES, N_OBS, CHILD_GRID, None)
    return cli.main(argv)


if __name__ == "__main__":
    import sys
    sys.exit(child_main(sys.argv[1:]))
