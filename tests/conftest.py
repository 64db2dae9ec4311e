"""Shared test setup: headless plotting, the real-data folder, quiet VTK."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")

REPO = Path(__file__).resolve().parents[1]
from stircasadi.datasets import data_dir

SHARED_DATA = data_dir()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real measured transients); tests that need a file skip if it is absent."""
    return SHARED_DATA
