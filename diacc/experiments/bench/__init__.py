"""Benchmarks behind ``diacc bench``: each module measures side by side in one run."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from diacc.fileio import open_append


def write_json_lines(records: Iterable[dict], out: str | None) -> None:
    """Print each record as one JSON line as soon as it is measured, and append it
    to ``out`` when given: the output of the sweep scripts in ``benchmarks/``.

    Flushed line by line (the records may be a generator that runs one episode
    each), so a long sweep shows its progress and a killed one keeps what it did.
    """
    for record in records:
        line = json.dumps(record)
        print(line, flush=True)
        if out:
            with open_append(Path(out)) as fh:
                fh.write(line + "\n")
