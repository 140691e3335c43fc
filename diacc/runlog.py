"""Recoveries and warnings go to one logger, shown on stderr and kept in the run's log file.

Faults that diacc recovers from (a restarted worker or simulator, a damaged
results file that is recomputed, an interrupted run that saved a checkpoint)
must not pass silently, yet must not stop the run either. They are logged on
the ``diacc`` logger: :func:`enable_stderr` (called by the CLI) prints each
as one ``diacc: warning: ...`` line, and :func:`run_log` appends them, with a
timestamp, to a file of the run directory or results directory
(``train.log``, ``eval.log``) so that the record outlives the terminal.
Milestones (a run's start with its :func:`config_digest`, its checkpoints,
its end) are logged at INFO level: in the file only, not on stderr.
Worker processes started inside :func:`run_log` find that file in the
environment (:data:`ENV_VAR`) and append to it too (:func:`join_parent_log`).
"""

from __future__ import annotations

import errno
import fcntl
import hashlib
import json
import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path
from typing import Any

from diacc.errors import DiaccError
from diacc.fileio import (
    OutputPathError,
    open_append,
    refuse_symlink,
    remove_temporaries,
    remove_tree,
)

log = logging.getLogger("diacc")
log.setLevel(logging.INFO)
#: Environment variable naming the active run log, for worker processes.
ENV_VAR = "DIACC_RUN_LOG"


def enable_stderr() -> None:
    """Print diacc's warnings on stderr as one line each (idempotent)."""
    if not any(getattr(h, "_diacc_stderr", False) for h in log.handlers):
        handler = _StderrHandler()
        handler.setLevel(logging.WARNING)
        handler.setFormatter(_OneLine())
        handler._diacc_stderr = True  # type: ignore[attr-defined]
        log.addHandler(handler)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time (it may be replaced, e.g. by tests)."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


class _OneLine(logging.Formatter):
    """``diacc: warning: message``, the same shape as the CLI's one-line errors."""

    def format(self, record: logging.LogRecord) -> str:
        return f"diacc: {record.levelname.lower()}: {record.getMessage()}"


@contextmanager
def run_log(path: Path) -> Iterator[None]:
    """Append diacc's log records to ``path`` while the block runs."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = _file_handler(path)
    log.addHandler(handler)
    previous = os.environ.get(ENV_VAR)
    os.environ[ENV_VAR] = str(path.resolve())
    try:
        yield
    finally:
        log.removeHandler(handler)
        handler.close()
        if previous is None:
            os.environ.pop(ENV_VAR, None)
        else:
            os.environ[ENV_VAR] = previous


def join_parent_log() -> None:
    """In a worker process: log to stderr and to the parent's run log, if it has one."""
    enable_stderr()
    path = os.environ.get(ENV_VAR)
    if path and not any(isinstance(h, logging.FileHandler) for h in log.handlers):
        log.addHandler(_file_handler(Path(path)))


class _NoFollowFileHandler(logging.FileHandler):
    """A FileHandler that appends to its file, never through a symbolic link."""

    def _open(self):
        return open_append(Path(self.baseFilename))


def _file_handler(path: Path) -> logging.FileHandler:
    refuse_symlink(path)
    handler = _NoFollowFileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    return handler


def config_digest(config: Any) -> str:
    """First 12 hex digits of the SHA-256 of a config dataclass as JSON (sorted keys).

    Logged with a run's start, so two logs show at a glance whether two runs
    had the same config (the config itself is in ``config.json``).
    """
    text = json.dumps(asdict(config), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


# --------------------------------------------------------------------------
# Run directories: one writer at a time, nothing replaced unasked
# --------------------------------------------------------------------------
#: Files whose presence means a directory holds a training run.
RUN_FILES = ("checkpoint.pt", "progress.jsonl", "config.json")
#: What ``--overwrite`` removes: a run's files, nothing else of the directory.
_RUN_OUTPUTS = (*RUN_FILES, "train.log", "tb")
LOCK_FILE = ".lock"


class RunDirError(DiaccError, RuntimeError):
    """A run or output directory cannot be used (in use, holds a run, not writable)."""


@contextmanager
def locked_dir(directory: Path, command: str) -> Iterator[None]:
    """Create ``directory`` if needed and hold its lock while the block runs.

    An ``flock`` on ``<directory>/.lock`` (holding the owner's pid, for the
    message): a second process gets a one-line :class:`RunDirError` instead of
    interleaving its files with the first's. The kernel drops the lock when
    its holder dies, so a lock file left by a killed run is simply taken over.
    A directory this call created is removed again if the block leaves it
    empty (a run refused before it wrote anything leaves no trace). A lock
    file that is a symbolic link is refused, not followed; with the lock held,
    temporaries of killed writers in the directory and its sub-folders
    (``checkpoint.pt.<pid>-<hex>.tmp``) are removed (warned).
    """
    directory = Path(directory)
    created = not directory.exists()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        refuse_symlink(directory / LOCK_FILE)
        fd = _lock(directory / LOCK_FILE, directory, command)
    except OutputPathError:
        raise
    except OSError as exc:
        raise RunDirError(
            f"cannot use {directory} as the {command} directory "
            f"({exc.strerror or type(exc).__name__})"
        ) from None
    try:
        _remove_stale_temporaries(directory)
        yield
    finally:
        (directory / LOCK_FILE).unlink(missing_ok=True)
        os.close(fd)  # releases the flock
        if created and not any(directory.iterdir()):
            directory.rmdir()


def _remove_stale_temporaries(directory: Path) -> None:
    """Remove (warned) what killed atomic writers left in ``directory`` and its sub-folders."""
    folders = [directory, *(p for p in directory.iterdir() if p.is_dir() and not p.is_symlink())]
    stale = [path for folder in folders for path in remove_temporaries(folder)]
    if stale:
        log.warning(
            "removed %d temporary file(s) of an interrupted write in %s (%s)",
            len(stale),
            directory,
            ", ".join(sorted(p.name for p in stale)),
        )


def _lock(path: Path, directory: Path, command: str) -> int:
    """Open and flock ``path``; retry if it was replaced meanwhile (its holder just released it)."""
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:  # became a link after the check above
                refuse_symlink(path)
            raise
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise RunDirError(
                f"{directory} is in use by another diacc {command} (process {holder}); "
                "wait for it to end or choose another directory"
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            return fd
        os.close(fd)


def claim_run_dir(run_dir: Path, resume: bool, overwrite: bool) -> None:
    """Refuse to start a new run over an existing one unless told to replace it.

    Without this a ``train`` into a finished run's directory replaced its
    checkpoint and appended to its ``progress.jsonl``. ``overwrite`` removes
    the previous run's files (only those) first; a run file that is a symbolic
    link is refused before anything is written (``--overwrite`` removes the
    link, never its target). Call with the lock held.
    """
    held = [name for name in RUN_FILES if os.path.lexists(run_dir / name)]
    replace = held and overwrite and not resume
    for name in () if replace else _RUN_OUTPUTS:
        refuse_symlink(run_dir / name)
    if held and not overwrite and not resume:
        raise RunDirError(
            f"{run_dir} already holds a run ({', '.join(held)}); continue it with --resume "
            "or replace it with --overwrite"
        )
    for name in _RUN_OUTPUTS if replace else ():
        remove_tree(run_dir / name)
