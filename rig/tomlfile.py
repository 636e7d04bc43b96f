"""Reading the suite's TOML files (rig configs, plans) with errors that name the file."""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any


def read_toml(path: str | Path, *, error: type[Exception] = ValueError,
              what: str = "file") -> dict[str, Any]:
    """The tables of the TOML file at ``path``.

    Parameters
    ----------
    path : str or Path
    error : exception class
        Raised (with a message naming the file) when the file is missing, unreadable, not text
        or not valid TOML: each caller's own error type (``ConfigError``, ``PlanError``).
    what : str
        What the file is, for the "does not exist" message (``"rig file"``, ``"plan file"``).
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{what} {path} does not exist")
    try:
        # utf-8-sig: editors on Windows save a byte-order mark, which TOML itself does not allow
        return tomllib.loads(path.read_text(encoding="utf-8-sig"))
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and inline tables recursively
        raise error(f"{path}: arrays or tables nested too deep to be a {what}") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file") from None
    except OSError as exc:
        raise error(f"{path}: cannot read it ({exc.strerror or exc})") from None
