"""``progress.jsonl``: one JSON object per finished update, appended by the trainer.

Read back by ``--resume`` (cut to the checkpoint's update) and by ``diacc plot
curves``; both read it here so that a damaged file (bytes that are not UTF-8,
a row that is not an object, a step counter that is not a whole number, a
value that is not a number) is the same one line naming the file and row,
never a traceback or a curve drawn from strings. A last line without its
newline that does not parse is what a killed trainer leaves mid-write: it is
dropped, not refused.
"""

from __future__ import annotations

import json
from pathlib import Path

from diacc.errors import DiaccError
from diacc.fileio import atomic_write

#: The two step counters every row holds.
COUNTERS = ("update", "global_step")


class ProgressError(DiaccError, ValueError):
    """``progress.jsonl`` is damaged, or does not agree with the run's checkpoint."""


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def read_rows(path: Path) -> list[dict]:
    """The rows of ``path`` (a torn last line dropped); one line if it is damaged."""
    data = Path(path).read_bytes()
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ProgressError(f"{path}:{line} is not UTF-8 text") from None
    lines = text.split("\n")
    rows = []
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except ValueError:
            if number == len(lines):  # no newline after it: a write cut short by a kill
                break
            raise ProgressError(f"{path}:{number} is not valid JSON") from None
        if not isinstance(row, dict):
            raise ProgressError(f"{path}:{number} is not a JSON object")
        for key in COUNTERS:
            value = row.get(key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                raise ProgressError(
                    f"{path}:{number}: {key!r} is not a whole number >= 0 ({value!r:.40})"
                )
        for key, value in row.items():
            if not (_is_number(value) or value is None):
                raise ProgressError(f"{path}:{number}: {key!r} is not a number ({value!r:.40})")
        rows.append(row)
    return rows


def check_agrees(rows: list[dict], path: Path, update: int, global_step: int) -> None:
    """One-line :class:`ProgressError` unless the row of ``update`` has ``global_step``.

    The trainer appends a row before it saves the checkpoint of that update,
    so a run's ``progress.jsonl`` always holds the checkpoint's row; a row
    that is missing or counts other steps means the two files come from
    different runs (resuming would cut one with the other's counter).
    """
    if update == 0:
        return
    steps = [row["global_step"] for row in rows if row["update"] == update]
    if not steps:
        raise ProgressError(
            f"{path} has no row for update {update}, the checkpoint's; the two files do not "
            "belong to one run"
        )
    if steps[-1] != global_step:
        raise ProgressError(
            f"{path} has update {update} at step {steps[-1]}, the checkpoint at step "
            f"{global_step}; the two files do not belong to one run"
        )


def keep_until(path: Path, rows: list[dict], update: int) -> None:
    """Rewrite ``path`` (atomically) with the rows up to ``update``: drops those of lost updates."""
    atomic_write(path, "".join(json.dumps(row) + "\n" for row in rows if row["update"] <= update))
