"""Shared fixtures."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

#: ``../shared/data`` beside the repository; ``GONIO_SHARED_DATA`` points elsewhere (a git
#: worktree that does not sit beside it).
SHARED_DATA = Path(os.environ.get("GONIO_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real photos, raws, probes, meshes); skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it ships beside the repository, "
                    "not in it)")
    return SHARED_DATA
