"""Shared pytest fixtures.

``shared_data``: the project's shared real data (``../shared/data`` next to the repository, as in
CI). Tests that need it skip with a clear reason when it is absent; small excerpts live in
``tests/data`` and are always available (``test_data``).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("FRSLAM_SHARED_DATA", REPO.parent / "shared" / "data"))
TEST_DATA = REPO / "tests" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(
            f"shared data not found at {SHARED_DATA} (set FRSLAM_SHARED_DATA or clone next to ../shared)"
        )
    return SHARED_DATA


@pytest.fixture(scope="session")
def test_data() -> Path:
    return TEST_DATA
