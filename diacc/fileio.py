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
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_target(path: Path) -> Iterator[Path]:
    """Yield a fresh temporary path beside ``path``; on a clean exit it replaces ``path``.

    For writers that need a path of their own (``torch.save``). If the block
    raises, the temporary file is removed and ``path`` is left as it was.
    """
    tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
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
