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


def _file_handler(path: Path) -> logging.FileHandler:
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    return handler


def config_digest(config: Any) -> str:
    """First 12 hex digits of the SHA-256 of a config dataclass as JSON (sorted keys).

    Logged with a run's start, so two logs show at a glance whether two runs
    had the same config (the config itself is in ``config.json``).
    """
    text = json.dumps(asdict(config), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]
