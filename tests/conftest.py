"""Shared fixtures: the real-data folder (skipped with a reason where it is missing)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("TORCHSFM_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository (or $TORCHSFM_DATA)."""
    if not (SHARED_DATA / "INDEX.md").exists():
        pytest.skip(f"real data not found at {SHARED_DATA} (set TORCHSFM_DATA)")
    return SHARED_DATA
