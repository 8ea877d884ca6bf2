"""Shared fixtures: a sphere and the shared data folder.

Real-data tests are those that take the ``shared_data`` fixture (directly or through another
fixture); they are marked ``real_data`` at collection (``pytest -m real_data`` runs them
alone). Without ``../shared/data`` they skip, except under CI (``LOGDESC_REQUIRE_SHARED_DATA``),
where the suite stops at once and any real-data test that skips fails instead.
"""

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


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "real_data: needs ../shared/data (ModelNet, the Bunny scans)")


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()):
            item.add_marker(pytest.mark.real_data)


def _skipped_for_missing_data(report) -> bool:
    """Whether a skip names the shared data (its folder or a file in it), not, say, an optional
    package that is not installed (``pytest.importorskip``)."""
    message = str(report.longrepr)
    return "shared data" in message or str(SHARED_DATA) in message or "/shared/data" in message


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """Under CI a real-data test may not skip for want of the data: a file missing from the
    shared data is a failure (a missing optional package still skips)."""
    outcome = yield
    report = outcome.get_result()
    if (report.skipped and os.environ.get(REQUIRE_SHARED_DATA) and item.get_closest_marker("real_data")
            and _skipped_for_missing_data(report)):
        report.outcome = "failed"
        report.longrepr = f"{REQUIRE_SHARED_DATA} is set but this real-data test skipped: {report.longrepr}"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA
