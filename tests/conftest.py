"""Shared pytest fixtures. Area tests live in tests/<area>/ with their own conftest.py where needed."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def shared_path(*parts: str) -> Path:
    """Path under ``../shared/`` beside the repo. Skips the test if missing, fails it under ``CI=true``."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        msg = f"{path} is missing (the shared data beside the repo)"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + "; under CI=true it must be present")
        pytest.skip(msg)
    return path


@pytest.fixture
def fabricslide_dir() -> Path:
    """``../shared/data/fabricslide`` (skip if missing, fail under CI=true)."""
    return shared_path("data", "fabricslide")


@pytest.fixture
def paper_path() -> Path:
    return shared_path("paper", "000_e930b09eb5eda72e.txt")
