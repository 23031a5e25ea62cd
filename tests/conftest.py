"""Shared fixtures. The real data lives beside the project, in ../shared/data."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ../shared/data (see its DATA.md); skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scan data not found at {SHARED_DATA} (../shared/data is absent)")
    return SHARED_DATA
