"""The code version recorded with every result (asks git when running from a checkout)."""
from __future__ import annotations

import functools
import subprocess
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path


@functools.cache
def code_version() -> str:
    """``gonio <version>`` plus ``+g<commit>`` when the code runs from a git checkout."""
    try:
        text = f"gonio {version('gonio')}"
    except PackageNotFoundError:
        text = "gonio (not installed)"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=Path(__file__).parent,
                                capture_output=True, text=True, timeout=5)
        if commit.returncode == 0 and commit.stdout.strip():
            text += f"+g{commit.stdout.strip()}"
    except (OSError, subprocess.SubprocessError):
        pass
    return text

