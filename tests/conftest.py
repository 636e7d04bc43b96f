"""Shared fixtures, and the heavy simulated sessions started in the background (background.py)."""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

import pytest

from background import JOBS, Background

#: ``../shared/data`` beside the repository; ``GONIO_SHARED_DATA`` points elsewhere (a git
#: worktree that does not sit beside it).
SHARED_DATA = Path(os.environ.get("GONIO_SHARED_DATA",
                                  Path(__file__).resolve().parents[2] / "shared" / "data"))
_BACKGROUND = pytest.StashKey[Background]()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """``../shared/data`` (real photos, raws, probes, meshes); skips when absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it ships beside the repository, "
                    "not in it)")
    return SHARED_DATA


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start the background jobs the collected tests use, in the order they are needed."""
    if session.config.option.collectonly:
        return
    first = {}
    for k, item in enumerate(session.items):
        for job in JOBS:
            if job.name not in first and job.used_by(item):
                first[job.name] = k
    jobs = sorted((job for job in JOBS if job.name in first), key=lambda job: first[job.name])
    session.config.stash[_BACKGROUND] = Background(Path(tempfile.mkdtemp(prefix="gonio-tests-")), jobs)


def pytest_terminal_summary(terminalreporter, config: pytest.Config) -> None:
    background = config.stash.get(_BACKGROUND, None)
    if background is not None and background.jobs:
        terminalreporter.write_line(background.summary())


def pytest_sessionfinish(session: pytest.Session) -> None:
    background = session.config.stash.get(_BACKGROUND, None)
    if background is not None:
        background.stop()


@pytest.fixture(scope="session")
def background(request) -> Background:
    """The jobs started after collection (:class:`background.Background`): ``folder(name)``."""
    return request.config.stash[_BACKGROUND]
