"""Shared fixtures: the real-data folder (skipped with a reason where it is missing), and the
global RNG seeded before every test."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("TORCHSFM_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` beside the repository (or $TORCHSFM_DATA)."""
    if not (SHARED_DATA / "INDEX.md").exists():
        pytest.skip(f"real data not found at {SHARED_DATA} (set TORCHSFM_DATA)")
    return SHARED_DATA


@pytest.fixture(autouse=True)
def seeded_global_rng() -> None:
    """Every test starts from one global RNG state, so a call that leaves ``generator`` out (and
    so draws from the global RNG, the documented policy) is as reproducible as one that passes it."""
    torch.manual_seed(0)
