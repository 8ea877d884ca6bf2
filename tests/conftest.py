"""Shared fixtures: a sphere and the shared data folder (skips when absent)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from .shapes import fibonacci_sphere

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
# Set by .ci/run: the real-data tests (ModelNet, the Bunny scans) must run, not skip.
REQUIRE_SHARED_DATA = "LOGDESC_REQUIRE_SHARED_DATA"


def pytest_sessionstart(session) -> None:
    """Stop at once, as a failure, when CI asks for the shared data and it is not there: without
    it every real-data test would skip and the suite would pass on synthetic shapes alone."""
    if os.environ.get(REQUIRE_SHARED_DATA) and not SHARED_DATA.is_dir():
        pytest.exit(f"{REQUIRE_SHARED_DATA} is set but the shared data is not at {SHARED_DATA}", returncode=1)


@pytest.fixture
def sphere() -> np.ndarray:
    return fibonacci_sphere(1024)


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA
