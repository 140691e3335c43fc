"""Hostile files and careless use (issue 22): untrusted files run no code, nothing is
silently overwritten or written outside ``--out``, every fault is one line.

One test (or group) per root cause; each failed on the code before the fix.
The CLI-level bad inputs are rows of the fault table in ``tests/test_faults.py``.
"""

from __future__ import annotations

import copy
import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from diacc.cli import main
from diacc.learn import checkpoint
from diacc.learn.checkpoint import CheckpointError, convert_checkpoint, load_checkpoint
from diacc.sim.maps import map_tag

SHIPPED = sorted((Path(__file__).resolve().parent.parent / "checkpoints").glob("*.pt"))[0]
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def _one_line_error(capsys, argv: list[str]) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err, err
    return err


# ----------------------------------------------------------------------------- 1: checkpoints
class _WritesAFile:
    """Unpickling this calls ``os.system``: what a hostile checkpoint would do."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.fixture
def shipped_payload() -> dict:
    return load_checkpoint(SHIPPED)


def test_malicious_checkpoint_runs_nothing(tmp_path, shipped_payload, capsys):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({**shipped_payload, "extra": _WritesAFile(marker)}, evil)
    with pytest.raises(CheckpointError, match="could run code"):
        load_checkpoint(evil)
    err = _one_line_error(capsys, ["eval", "--policy", str(evil), "--out", str(tmp_path / "o")])
    assert "refused: loading it could run code" in err
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(evil.read_bytes())
    err = _one_line_error(capsys, ["train", "--resume", "--run-dir", str(run), "--steps", "2000"])
    assert "could run code" in err
    with pytest.raises(CheckpointError, match="cannot be converted"):
        convert_checkpoint(evil, tmp_path / "converted.pt")
    assert not marker.exists(), "the checkpoint's pickle ran code"


def test_damaged_checkpoints_are_one_line(tmp_path, shipped_payload):
    cases = {
        "no 'actor'": {k: v for k, v in shipped_payload.items() if k != "actor"},
        "'config' is a list": {**shipped_payload, "config": [1, 2]},
        "'update' is a str": {**shipped_payload, "update": "7"},
        "'rng'": {**shipped_payload, "rng": {"python": None}},
        "not a tensor": {**shipped_payload, "critic": {"w": [1.0]}},
        "unusable config": {**shipped_payload, "config": {"env": {"sim": {"cav": 3}}}},
        "not a diacc checkpoint": [1, 2, 3],
        "format 7": {**shipped_payload, "format": 7},
    }
    for expected, payload in cases.items():
        path = tmp_path / "bad.pt"
        torch.save(payload, path)
        with pytest.raises(CheckpointError) as info:
            load_checkpoint(path)
        assert expected in str(info.value) and "\n" not in str(info.value), str(info.value)


def test_old_format_is_refused_with_the_command_that_converts_it(tmp_path, shipped_payload, capsys):
    old = copy.deepcopy(shipped_payload)
    rng = old["rng"]
    old["format"] = 1
    old["rng"] = {  # format 1: Python's and numpy's own state tuples (numpy: an ndarray)
        "python": (rng["python"]["version"], tuple(rng["python"]["state"].tolist()), None),
        "numpy": ("MT19937", rng["numpy"]["key"].numpy().astype(np.uint32), 624, 0, 0.0),
        "torch": rng["torch"],
        "cuda": None,
    }
    path = tmp_path / "old.pt"
    torch.save(old, path)
    with pytest.raises(
        CheckpointError, match=f"convert it once with: diacc convert-checkpoint {path}"
    ):
        load_checkpoint(path)
    capsys.readouterr()
    assert main(["convert-checkpoint", str(path)]) == 0
    new = load_checkpoint(path)
    for part in ("actor", "critic", "value_norm"):
        for name, tensor in shipped_payload[part].items():
            assert torch.equal(new[part][name], tensor)
    assert new["rng"]["numpy"]["pos"] == 624


def test_a_failed_checkpoint_write_keeps_the_old_file_and_no_tmp(tmp_path, monkeypatch):
    from test_mappo import tiny_config

    from diacc.learn.mappo import make_agent

    cfg = tiny_config(tmp_path)
    agent = make_agent(cfg, torch.device("cpu"))
    path = tmp_path / "checkpoint.pt"
    checkpoint.save_checkpoint(path, agent, cfg, 1, 20)
    before = path.read_bytes()

    def disk_full(obj, f):
        Path(f).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(checkpoint.torch, "save", disk_full)
    with pytest.raises(CheckpointError, match="No space left on device.*unchanged"):
        checkpoint.save_checkpoint(path, agent, cfg, 2, 40)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")) == []


# ----------------------------------------------------------------------------- 2: run identity
def test_run_identity_is_the_map_content_not_its_file_name(tmp_path):
    a, b = tmp_path / "a" / "road.toml", tmp_path / "b" / "road.toml"
    for path, length in ((a, 300), (b, 400)):
        path.parent.mkdir()
        path.write_text(_road(length))
    assert map_tag(a) != map_tag(b) and map_tag(a).startswith("road-")
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "road.toml").write_bytes(a.read_bytes())
    assert map_tag(tmp_path / "c" / "road.toml") == map_tag(a)
    assert map_tag("train-25") == "train-25"


def _road(length_m: float, name: str = "road") -> str:
    return (
        f'name = "{name}"\nlane_width_m = 3.2\n[[segments]]\nkind = "multilane"\n'
        f"length_m = {length_m}\nlanes = 3\nspeed_limit_mps = 25.0\n"
    )


# ----------------------------------------------------------------------------- 3: inside --out
@pytest.mark.parametrize("where", ["absolute", "relative"])
def test_cell_results_stay_inside_out(tmp_path, monkeypatch, capsys, where):
    maps = tmp_path / "maps"
    maps.mkdir()
    (maps / "road.toml").write_text(_road(300))
    monkeypatch.chdir(tmp_path)
    road = str(maps / "road.toml") if where == "absolute" else "maps/road.toml"
    grid = tmp_path / "grid.toml"
    grid.write_text(f'[[cells]]\nmap = "{road}"\nn_vehicles = 6\ncav_penetration = 0.5\n'
                    'style_mix = "D1"\n')  # fmt: skip
    out = tmp_path / "out"
    argv = ["eval", "--policy", "cooperative", "--grid", str(grid), "--episodes", "1"]
    argv += ["--episode-steps", "3", "--out", str(out), "--no-progress"]
    assert main(argv) == 0, capsys.readouterr().err
    assert sorted(p.name for p in maps.iterdir()) == ["road.toml"]
    written = list((out / "cells").glob("*.episodes.csv"))
    assert len(written) == 1 and written[0].name.startswith(map_tag(road) + "_N6")
    capsys.readouterr()
    assert main(argv) == 0  # the rerun finds the finished cell (it crashed or re-ran before)
    assert "0 cells run, 1 already done" in capsys.readouterr().out


# ----------------------------------------------------------------------------- 4: SUMO cache
def test_sumo_cache_names_come_from_content(tmp_path, caplog):
    from diacc.sim.backends.sumo.net import _complete_network, build_network
    from diacc.sim.maps import parse_map
    from diacc.tomlfile import read_toml

    source = tmp_path / "m.toml"
    source.write_text(_road(300, name="../../escaped/x"))
    road = parse_map(read_toml(source, ValueError))
    cache = tmp_path / "deep" / "cache"
    net, route = build_network(road, cache)
    assert net.parent == cache and route.parent == cache
    assert not list(tmp_path.glob("escaped*")) and "escaped" not in net.name
    # A truncated network (a build killed mid-write by an older diacc) is rebuilt.
    good = net.read_bytes()
    net.write_bytes(good[: len(good) // 2])
    with caplog.at_level("WARNING", logger="diacc"):
        assert build_network(road, cache)[0] == net
    assert _complete_network(net, road) and "damaged; rebuilding" in caplog.text
    # An unusable cache folder (here: a file where the folder should be) falls back, warned.
    blocker = tmp_path / "file"
    blocker.write_text("")
    with caplog.at_level("WARNING", logger="diacc"):
        net2, _ = build_network(road, blocker / "sumo")
    assert net2.exists() and "is unusable" in caplog.text


# ----------------------------------------------------------------------------- 5: signals
def _descendants(pid: int) -> set[int]:
    from test_faults import _descendants as descendants

    return {child for child, _ in descendants(pid)}


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _signal_ends_every_child(tmp_path, argv, ready, signum=signal.SIGTERM, times=1) -> str:
    """Run ``diacc argv``; once ``ready(command lines of its descendants)``, send ``signum``
    (``times`` times, 0.5 s apart).

    Checks the exit status (128 + signum) and, by pid, that every descendant seen
    before the signal is gone within 20 s. Returns stderr.
    """
    from test_faults import _descendants as descendants

    # SIGINT as from a terminal: a suite run in the background by a non-interactive shell
    # ignores SIGINT, and so would the command (POSIX), which would then run on.
    proc = subprocess.Popen(
        [sys.executable, "-m", "diacc.cli", *argv], env=ENV, stderr=subprocess.PIPE, text=True,
        cwd=tmp_path, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    deadline, children = time.monotonic() + 120, {}
    try:
        while time.monotonic() < deadline and not ready(list(children.values())):
            assert proc.poll() is None, "the command ended before the signal"
            children.update(descendants(proc.pid))
            time.sleep(0.1)
        assert ready(list(children.values())), f"not ready: {list(children.values())}"
        time.sleep(1.0)  # busy with the episodes
        children.update(descendants(proc.pid))
        for _ in range(times):
            proc.send_signal(signum)
            time.sleep(0.5)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signum, err
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and any(_alive(p) for p in children):
        time.sleep(0.1)
    left = [children[p] for p in children if _alive(p)]
    for pid in [p for p in children if _alive(p)]:
        os.kill(pid, signal.SIGKILL)  # leave the machine clean for the next test
    assert not left, f"children outlived the command: {left}"
    assert "Traceback" not in err, err
    return err


def _count(word: str, n: int):
    return lambda commands: sum(word in cmd for cmd in commands) >= n


def _grid(tmp_path) -> Path:
    grid = tmp_path / "grid.toml"
    grid.write_text('[product]\nmap = ["train-25"]\nn_vehicles = [20, 25]\n'
                    'cav_penetration = [0.4]\nstyle_mix = ["D1"]\n')  # fmt: skip
    return grid


EVAL = ["eval", "--policy", "pure-hdv", "--episodes", "200", "--out", "out", "--no-progress"]


def test_sigterm_to_eval_with_workers_ends_every_child(tmp_path):
    argv = [*EVAL, "--grid", str(_grid(tmp_path)), "--workers", "2"]
    _signal_ends_every_child(tmp_path, argv, _count("multiprocessing", 3))  # + resource tracker


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
def test_signal_to_sumo_eval_with_workers_ends_every_child(tmp_path, signum):
    """Pool workers die at once; their SUMO workers read a reset connection and exit quietly.

    SIGHUP (a closed terminal) once killed the command alone (issue 46)."""
    argv = [*EVAL, "--grid", str(_grid(tmp_path)), "--workers", "2", "--backend", "sumo"]
    _signal_ends_every_child(tmp_path, argv, _count("sumo.worker", 2), signum)


@pytest.mark.parametrize(("vector", "times"), [("sync", 1), ("process", 2)])
def test_sigterm_to_sumo_train_ends_every_child(tmp_path, vector, times):
    """One SIGTERM checkpoints after the update, a second stops at once: 143 both times."""
    argv = ["train", "--backend", "sumo", "--envs", "2", "--steps", "100000", "--run-dir", "run"]
    argv += ["--set", f"vector={vector}"]
    log = tmp_path / "run" / "train.log"

    def training(commands) -> bool:  # workers up and the loop started (its handler set)
        return _count("sumo.worker", 2)(commands) and log.exists() and "start:" in log.read_text()

    err = _signal_ends_every_child(tmp_path, argv, training, times=times)
    assert ("checkpoint saved" if times == 1 else "stopped at once by a second SIGTERM") in err


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_signal_to_ray_eval_ends_every_child(tmp_path, signum):
    """The local Ray instance (GCS, raylet, its workers) goes with the command.

    ray.init installs a SIGTERM handler that exits with status 1 and Ray turns the
    CLI's exception into a bare KeyboardInterrupt: still 143, still every child gone.
    """
    pytest.importorskip("ray")
    argv = [*EVAL, "--grid", str(_grid(tmp_path)), "--engine", "ray", "--ray-cpus", "2"]
    err = _signal_ends_every_child(tmp_path, argv, _count("ray::_run_cell", 2), signum)
    assert f"diacc: {'terminated (SIGTERM)' if signum == signal.SIGTERM else 'interrupted'}" in err


@pytest.mark.slow  # about 30 s on 2 busy cores; the Ray eval test above is the short one
def test_sigterm_to_ray_sweep_with_sumo_ends_every_child(tmp_path):
    """Ray tasks training on SUMO: raylet, task workers and their SUMO workers all end."""
    pytest.importorskip("ray")
    argv = ["sweep", "--seeds", "1,2", "--steps", "100000", "--envs", "2", "--backend", "sumo"]
    argv += ["--engine", "ray", "--ray-cpus", "2", "--out-dir", "runs"]
    _signal_ends_every_child(tmp_path, argv, _count("sumo.worker", 4))


# ----------------------------------------------------------------------------- 8: hangs
def _naive_lane_end_m(road) -> np.ndarray:
    """The old definition, searched forward from every segment (quadratic)."""
    exists, ends = road.lane_exists(), road.segment_ends_m
    out = np.full(exists.shape, np.inf)
    for s in range(len(road.segments)):
        for lane in range(road.max_lanes):
            for t in range(s, len(road.segments)):
                if not exists[t, lane]:
                    out[s, lane] = ends[t - 1] if t > 0 else 0.0
                    break
    return out


def test_lane_end_is_linear_in_segments():
    from diacc.sim.maps import Map, Segment

    lanes = [3, 2, 3, 1, 3]
    segments = tuple(Segment("multilane", 10.0, lanes[i % len(lanes)], 20.0) for i in range(60_000))
    road = Map("long", "", 3.2, "left", segments)
    start = time.perf_counter()
    ends = road.lane_end_m()
    assert time.perf_counter() - start < 5.0
    assert ends.shape == (60_000, 3)
    for side in ("left", "right"):
        small = Map("small", "", 3.2, side, segments[:200])
        assert np.array_equal(small.lane_end_m(), _naive_lane_end_m(small))


# ----------------------------------------------------------------------------- 7: one line
def test_damaged_results_and_logs_are_one_line(tmp_path, capsys):
    grid = tmp_path / "grid.toml"
    grid.write_text('[[cells]]\nmap = "train-25"\nn_vehicles = 6\ncav_penetration = 0.5\n'
                    'style_mix = "D1"\n')  # fmt: skip
    out = tmp_path / "out"
    argv = ["eval", "--policy", "cooperative", "--grid", str(grid), "--episodes", "1"]
    argv += ["--episode-steps", "3", "--no-progress", "--out"]
    assert main([*argv, str(out)]) == 0
    # An --out that is a file
    err = _one_line_error(capsys, [*argv, str(grid)])
    assert f"cannot use {grid} as the eval directory" in err
    # A garbled meta.json
    (out / "meta.json").write_text("{garbled")
    assert "meta.json: damaged (not valid JSON)" in _one_line_error(capsys, [*argv, str(out)])
    assert "meta.json: damaged" in _one_line_error(capsys, ["table", str(out)])
    # A non-numeric field in episodes.csv
    episodes = out / "episodes.csv"
    header, row = episodes.read_text().splitlines()[:2]
    column = header.split(",").index("mean_speed_mps")
    fields = row.split(",")
    fields[column] = "fast"
    episodes.write_text(header + "\n" + ",".join(fields) + "\n")
    err = _one_line_error(capsys, ["table", str(out)])
    assert "episodes.csv:2: field 'mean_speed_mps' is not a number ('fast')" in err
    # A row of progress.jsonl that is not a record
    run = tmp_path / "run"
    run.mkdir()
    (run / "progress.jsonl").write_text('{"update": 1, "global_step": 20}\n[1, 2]\n')
    err = _one_line_error(capsys, ["plot", "curves", str(run), "--out", str(tmp_path / "c")])
    assert "progress.jsonl:2 is not a JSON object" in err


def test_a_locked_results_directory_is_refused(tmp_path, capsys):
    from diacc.runlog import locked_dir

    out = tmp_path / "out"
    with locked_dir(out, "eval"):
        err = _one_line_error(
            capsys, ["eval", "--policy", "pure-hdv", "--episodes", "1", "--out", str(out)]
        )
    assert "is in use by another diacc eval" in err
