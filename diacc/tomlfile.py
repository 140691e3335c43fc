"""Read a TOML data file, turning syntax errors into a one-line error of the caller's type."""

from __future__ import annotations

import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


def read_toml(path: Path, error: type[Exception]) -> dict:
    """Parse ``path``; raise ``error("<path>: not valid TOML (...)")`` if it is broken."""
    try:
        return tomllib.loads(Path(path).read_text())
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML ({str(exc).splitlines()[0]})") from None
