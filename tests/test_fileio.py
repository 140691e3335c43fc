"""diacc.fileio: the one atomic-write helper (checkpoints, results, manifest, SUMO cache)."""

from __future__ import annotations

import os
import stat

import pytest

from diacc.fileio import atomic_target, atomic_write


def test_atomic_write_replaces_text_and_bytes_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "meta.json"
    atomic_write(path, "old\n")
    assert path.read_text() == "old\n"
    atomic_write(path, b"\x00new")
    assert path.read_bytes() == b"\x00new"
    assert [p.name for p in tmp_path.iterdir()] == ["meta.json"]


def test_a_failed_write_keeps_the_old_file_and_removes_the_temporary_one(tmp_path):
    path = tmp_path / "checkpoint.pt"
    atomic_write(path, b"old")
    with pytest.raises(OSError, match="No space"):
        with atomic_target(path) as tmp:
            tmp.write_bytes(b"part")
            raise OSError(28, "No space left on device")
    assert path.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["checkpoint.pt"]


def test_temporary_names_differ_per_write_and_files_get_umask_permissions(tmp_path):
    path = tmp_path / "net.xml"
    with atomic_target(path) as first, atomic_target(path) as second:
        assert first != second and first.parent == second.parent == tmp_path
        first.write_text("a")
        second.write_text("b")
    assert path.read_text() == "a"  # the outer block ends last and wins
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask
