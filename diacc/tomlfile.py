"""Read TOML and JSON data files; syntax and encoding errors become one-line errors of the
caller's type."""

from __future__ import annotations

import json
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - exercised on Python 3.10 only
    import tomli as tomllib


def read_json_object(path: Path, error: type[Exception]) -> dict:
    """Parse a JSON file holding one object; raise ``error("<path>: ...")`` (one line) if not.

    For the files diacc writes and reads back (``config.json``, ``meta.json``):
    a garbled or hand-edited one is a one-line error, not a traceback.
    """
    try:
        data = json.loads(Path(path).read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError):
        raise error(f"{path}: damaged (not valid JSON)") from None
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or type(exc).__name__})") from None
    if not isinstance(data, dict):
        raise error(f"{path}: damaged (a JSON {type(data).__name__}, not an object)")
    return data


def read_toml(path: Path, error: type[Exception]) -> dict:
    """Parse ``path``; raise ``error("<path>: not valid TOML (...)")`` if it is broken."""
    try:
        return tomllib.loads(Path(path).read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at offset "
                    f"{exc.start}); TOML files must be UTF-8") from None  # fmt: skip
    except tomllib.TOMLDecodeError as exc:
        raise error(f"{path}: not valid TOML ({str(exc).splitlines()[0]})") from None
    except IsADirectoryError:
        raise error(f"{path}: is a directory, not a TOML file") from None
    except OSError as exc:
        raise error(f"{path}: cannot be read ({exc.strerror or type(exc).__name__})") from None
    except RecursionError:  # a file of thousands of nested arrays or tables
        raise error(f"{path}: not valid TOML (nested too deeply)") from None
