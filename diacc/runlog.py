"""Recoveries and warnings go to one logger, shown on stderr and kept in the run's log file.

Faults that diacc recovers from (a restarted worker or simulator, a damaged
results file that is recomputed, an interrupted run that saved a checkpoint)
must not pass silently, yet must not stop the run either. They are logged on
the ``diacc`` logger: :func:`enable_stderr` (called by the CLI) prints each
as one ``diacc: warning: ...`` line, and :func:`run_log` appends them, with a
timestamp, to a file of the run directory or results directory
(``train.log``, ``eval.log``) so that the record outlives the terminal.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

log = logging.getLogger("diacc")
log.setLevel(logging.INFO)


def enable_stderr() -> None:
    """Print diacc's warnings on stderr as one line each (idempotent)."""
    if not any(getattr(h, "_diacc_stderr", False) for h in log.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setLevel(logging.WARNING)
        handler.setFormatter(_OneLine())
        handler._diacc_stderr = True  # type: ignore[attr-defined]
        log.addHandler(handler)


class _OneLine(logging.Formatter):
    """``diacc: warning: message``, the same shape as the CLI's one-line errors."""

    def format(self, record: logging.LogRecord) -> str:
        return f"diacc: {record.levelname.lower()}: {record.getMessage()}"


@contextmanager
def run_log(path: Path) -> Iterator[None]:
    """Append diacc's log records to ``path`` while the block runs."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    log.addHandler(handler)
    try:
        yield
    finally:
        log.removeHandler(handler)
        handler.close()
