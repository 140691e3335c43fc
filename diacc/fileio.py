"""Atomic file writes: a reader sees the old file or the new one, never half of one.

Checkpoints, result tables, the reproduction manifest and the SUMO network
cache are all written the same way: into a temporary file next to the target,
which then replaces it with one ``os.replace`` (atomic on POSIX within one
file system). A run killed mid-write, a full disk or two processes building
the same cache file therefore never leave a torn file behind.

The temporary name is unique per write (process id and a random suffix), so
concurrent writers of one path do not share a temporary file; it is created
with the ordinary ``open`` permissions (umask), unlike ``tempfile.mkstemp``'s
0600, so a result file is as readable as any other file diacc writes.

One rule for every file diacc writes: it never writes through a symbolic link
it did not create (:func:`refuse_symlink`, ``O_NOFOLLOW`` in :func:`open_append`),
since a planted link (``train.log -> ~/.bashrc``) would send its bytes to the
link's target; such a path is one :class:`OutputPathError` line. Temporaries
left by a killed writer (``checkpoint.pt.<pid>-<hex>.tmp`` after ``kill -9``)
are removed by the next writer of that directory (:func:`remove_temporaries`).
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

from diacc.errors import DiaccError


class OutputPathError(DiaccError, RuntimeError, OSError):
    """A path diacc would write is a link it did not create, a folder, or cannot be written.

    ``reason`` is the cause alone (``No space left on device``), for callers
    that word their own message. Also an ``OSError``: code that handles a
    failed write keeps handling it.
    """

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason or message

    def __str__(self) -> str:
        return str(self.args[0])


def check_output_file(path: Path) -> None:
    """Before any work: one-line :class:`OutputPathError` unless a file can be written at ``path``.

    Not a link, not a folder, and its folder exists as a writable folder or can
    be created in one (a table computed for minutes and then not written helps
    nobody).
    """
    path = Path(path)
    refuse_symlink(path)
    if path.is_dir():
        raise OutputPathError(f"{path} is a folder; give the name of a file to write")
    folder = path.parent
    while not os.path.lexists(folder) and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise OutputPathError(f"cannot write {path} ({folder} is not a folder)")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise OutputPathError(f"cannot write {path} ({folder} is not writable)")


def check_output_dir(directory: Path) -> None:
    """One-line :class:`OutputPathError` unless ``directory``, if there, is a writable folder."""
    directory = Path(directory)
    if os.path.lexists(directory) and not directory.is_dir():
        raise OutputPathError(f"cannot write into {directory} (not a folder)")
    if directory.is_dir() and not os.access(directory, os.W_OK | os.X_OK):
        raise OutputPathError(f"cannot write into {directory} (not writable)")


def refuse_symlink(path: Path) -> None:
    """One-line :class:`OutputPathError` if ``path`` itself is a symbolic link (``lstat``)."""
    if os.path.islink(path):
        raise OutputPathError(
            f"{path} is a symbolic link; diacc does not write through links it did not "
            "create (remove the link or choose another path)"
        )


def open_append(path: Path) -> TextIO:
    """``path`` opened for appending text (UTF-8), created if missing, never through a link."""
    try:
        fd = os.open(
            path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666
        )
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            refuse_symlink(path)
        raise
    return os.fdopen(fd, "a", encoding="utf-8")


def remove_tree(path: Path) -> None:
    """Remove a file or folder; a symbolic link is removed itself, its target left alone."""
    if os.path.islink(path) or not path.is_dir():
        path.unlink(missing_ok=True)
    else:
        shutil.rmtree(path)


#: The name :func:`atomic_target` gives its temporaries: ``<name>.<pid>-<8 hex>.tmp``.
_TEMPORARY = re.compile(r".+\.[0-9]+-[0-9a-f]{8}\.tmp")


def remove_temporaries(directory: Path) -> list[Path]:
    """Remove the temporaries a killed writer left in ``directory``; returns them.

    Call with the directory's lock held (no live writer of it can own one).
    """
    stale = [p for p in directory.glob("*.tmp") if _TEMPORARY.fullmatch(p.name)]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


@contextmanager
def atomic_target(path: Path) -> Iterator[Path]:
    """Yield a fresh temporary path beside ``path``; on a clean exit it replaces ``path``.

    For writers that need a path of their own (``torch.save``). If the block
    raises, the temporary file is removed and ``path`` is left as it was; an
    ``OSError`` (disk full, read-only folder) becomes a one-line
    :class:`OutputPathError`. A ``path`` that is a symbolic link is refused.
    """
    refuse_symlink(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OutputPathError):
            raise
        reason = exc.strerror or type(exc).__name__
        raise OutputPathError(f"cannot write {path} ({reason})", reason) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write(path: Path, data: bytes | str) -> None:
    """Write ``data`` (bytes as they are, text in the default encoding) to ``path`` atomically."""
    with atomic_target(path) as tmp:
        if isinstance(data, str):
            tmp.write_text(data)
        else:
            tmp.write_bytes(data)
