"""Hostile input, third pass (issue 46): links, damaged run state, output paths, the API.

One test (or group) per root cause; each failed on 822aaa9. A passing case
gives a one-line error and changes nothing on disk.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from test_mappo import tiny_config

from diacc.cli import main
from diacc.fileio import UnsafePathError, atomic_write
from diacc.learn.mappo import train
from diacc.runlog import claim_run_dir, locked_dir


def _one_line_error(capsys, argv: list[str]) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err, err
    return err


def _snapshot(folder: Path) -> dict[str, bytes | str]:
    """Every entry under ``folder``: file bytes, or a link's target (links not followed)."""
    out = {}
    for path in sorted(folder.rglob("*")):
        key = str(path.relative_to(folder))
        if path.is_symlink():
            out[key] = "-> " + os.readlink(path)
        elif path.is_file():
            out[key] = path.read_bytes()
    return out


@pytest.fixture(scope="module")
def run_once(tmp_path_factory) -> Path:
    """A tiny run of one update (checkpoint, progress, config, log, tb/)."""
    cfg = tiny_config(tmp_path_factory.mktemp("once"))
    return train(cfg, progress=False, stop_after_updates=1)


# ----------------------------------------------------------------------------- 1: links
@pytest.mark.parametrize("name", [".lock", "train.log", "progress.jsonl", "config.json", "tb"])
def test_train_never_writes_through_a_planted_link(tmp_path, name):
    precious = tmp_path / "precious"
    precious.write_text("keep me\n")
    cfg = tiny_config(tmp_path)
    run = Path(cfg.run_dir)
    run.mkdir()
    (run / name).symlink_to(precious)
    before = _snapshot(tmp_path)
    with pytest.raises(UnsafePathError, match=f"{name} is a symbolic link") as info:
        train(cfg, progress=False, stop_after_updates=1)
    assert "\n" not in str(info.value)
    assert _snapshot(tmp_path) == before


def test_eval_never_writes_through_a_planted_link(tmp_path, capsys):
    precious = tmp_path / "precious"
    precious.write_text("keep me\n")
    argv = ["eval", "--policy", "pure-hdv", "--episodes", "1", "--episode-steps", "3"]
    argv += ["--no-progress", "--out", str(tmp_path / "out")]
    for name in (".lock", "eval.log", "meta.json"):
        (tmp_path / "out").mkdir(exist_ok=True)
        (tmp_path / "out" / name).symlink_to(precious)
        before = _snapshot(tmp_path)
        assert "is a symbolic link" in _one_line_error(capsys, argv)
        assert _snapshot(tmp_path) == before
        (tmp_path / "out" / name).unlink()


def test_overwrite_removes_a_linked_tb_folder_not_its_target(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "events").write_text("keep")
    (run / "tb").symlink_to(elsewhere, target_is_directory=True)
    with locked_dir(run, "train"):
        claim_run_dir(run, resume=False, overwrite=True)
    assert not os.path.lexists(run / "tb") and (elsewhere / "events").read_text() == "keep"


def test_atomic_writes_refuse_a_link_and_killed_writes_are_cleaned_on_the_next_start(
    run_once, tmp_path, caplog
):
    target = tmp_path / "target"
    target.write_text("keep")
    (tmp_path / "meta.json").symlink_to(target)
    with pytest.raises(UnsafePathError):
        atomic_write(tmp_path / "meta.json", "x")
    assert target.read_text() == "keep"
    # What kill -9 during torch.save leaves: temporaries beside the checkpoint and the cells.
    stale = [
        run_once / "checkpoint.pt.4242-0badcafe.tmp",
        run_once / "cells" / "a.csv.7-01234567.tmp",
    ]
    (run_once / "cells").mkdir()
    for path in stale:
        path.write_bytes(b"partial")
    (run_once / "notes.tmp").write_text("mine")  # not a diacc temporary name: kept
    cfg = tiny_config(run_once.parent)
    train(cfg, resume=True, progress=False, stop_after_updates=1)
    assert not any(p.exists() for p in stale) and (run_once / "notes.tmp").exists()
    assert "removed 2 temporary file(s)" in caplog.text
