"""Hostile input, third pass (issue 46): links, damaged run state, output paths, the API.

One test (or group) per root cause; each failed on 822aaa9. A passing case
gives a one-line error and changes nothing on disk.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from test_mappo import tiny_config
from test_security import _one_line_error

import diacc
from diacc.cli import main
from diacc.config import override
from diacc.errors import DiaccError
from diacc.fileio import OutputPathError, atomic_write
from diacc.learn.checkpoint import CheckpointError, load_checkpoint
from diacc.learn.mappo import train
from diacc.learn.progress import ProgressError, read_rows
from diacc.runlog import claim_run_dir, locked_dir


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
    with pytest.raises(OutputPathError, match=f"{name} is a symbolic link") as info:
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
    with pytest.raises(OutputPathError):
        atomic_write(tmp_path / "meta.json", "x")
    assert target.read_text() == "keep"
    # What kill -9 during torch.save leaves: temporaries beside the checkpoint and the cells.
    run = _damaged_copy(run_once, tmp_path, lambda payload: None)
    stale = [run / "checkpoint.pt.4242-0badcafe.tmp", run / "cells" / "a.csv.7-01234567.tmp"]
    (run / "cells").mkdir()
    for path in stale:
        path.write_bytes(b"partial")
    (run / "notes.tmp").write_text("mine")  # not a diacc temporary name: kept
    train(_resume_config(run_once, run), resume=True, progress=False, stop_after_updates=1)
    assert not any(p.exists() for p in stale) and (run / "notes.tmp").exists()
    assert "removed 2 temporary file(s)" in caplog.text


# ----------------------------------------------------------------------------- 2: run state
def _resume_config(run_once: Path, run: Path):
    """The tiny run's config, living in ``run``."""
    return override(tiny_config(run_once.parent), {"run_dir": str(run)})


def _damaged_copy(run_once: Path, tmp_path: Path, damage) -> Path:
    """A copy of the tiny run whose checkpoint payload went through ``damage``."""
    run = tmp_path / "run"
    shutil.copytree(run_once, run)
    payload = torch.load(run / "checkpoint.pt", weights_only=True)
    damage(payload)
    torch.save(payload, run / "checkpoint.pt")
    return run


def _set(path: str, value):
    """A damage that sets ``payload[a][b]...`` (``path`` = "a/b") to ``value`` (or calls it)."""

    def damage(payload):
        *parents, last = (int(key) if key.isdigit() else key for key in path.split("/"))
        node = payload
        for key in parents:
            node = node[key]
        node[last] = value(node[last]) if callable(value) else value

    return damage


RUN_STATE_DAMAGE = {
    "optimiser: a group more": (
        _set("optimizer/param_groups", lambda groups: groups + groups),
        "damaged optimiser state (2 parameter groups, not 1)",
    ),
    "optimiser: a moment's shape": (
        _set("optimizer/state/0/exp_avg", lambda t: t.flatten()[:1]),
        "exp_avg of parameter 0 does not have its parameter's shape",
    ),
    "optimiser: a parameter less": (
        _set("optimizer/param_groups/0/params", lambda ids: ids[:-1]),
        "parameter group 0 has",
    ),
    "torch rng size": (_set("rng/torch", lambda t: t[:100]), "is damaged: 'rng'"),
    "python rng position": (
        _set("rng/python/state", lambda t: torch.cat([t[:-1], torch.tensor([9999])])),
        "is damaged: 'rng'",
    ),
    "numpy key range": (_set("rng/numpy/key", lambda t: t + 2**40), "numpy key"),
    "value normaliser keys": (
        _set("value_norm", lambda d: {"mean": d["running_mean"]}),
        "damaged value normaliser",
    ),
    "step counter": (
        _set("global_step", 999),
        "has update 1 at step 40, the checkpoint at step 999",
    ),
}


def _resume_error(run_once: Path, run: Path) -> str:
    """The one-line error of resuming the tiny run copied to ``run``."""
    with pytest.raises(DiaccError) as info:
        train(_resume_config(run_once, run), resume=True, progress=False, stop_after_updates=1)
    assert "\n" not in str(info.value)
    return str(info.value)


@pytest.mark.parametrize("case", list(RUN_STATE_DAMAGE))
def test_damaged_run_state_is_one_line_and_changes_nothing(run_once, tmp_path, case):
    damage, expected = RUN_STATE_DAMAGE[case]
    run = _damaged_copy(run_once, tmp_path, damage)
    before = _snapshot(run)
    assert expected in _resume_error(run_once, run)
    assert _snapshot(run) == before


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        (b'{"update": 1, "global_step": 40}\n\xff\xfe\n', "progress.jsonl:2 is not UTF-8 text"),
        (b'{"update": "1", "global_step": 40}\n', "'update' is not a whole number"),
        (b'{"update": 1, "global_step": 40, "team_reward": "high"}\n', "'team_reward' is not a"),
        (b'{"update": 1, "global_step": 40}\n[1]\n', "progress.jsonl:2 is not a JSON object"),
        (b'{"update": 2, "global_step": 80}\n', "has no row for update 1"),
    ],
)
def test_a_damaged_progress_file_is_one_line_for_resume_and_plot(
    run_once, tmp_path, capsys, content, expected
):
    run = _damaged_copy(run_once, tmp_path, lambda payload: None)
    (run / "progress.jsonl").write_bytes(content)
    before = _snapshot(run)
    assert expected in _resume_error(run_once, run)
    assert _snapshot(run) == before
    if "no row" not in expected:  # plot reads rows, not the checkpoint
        out = str(tmp_path / "curves")
        assert expected in _one_line_error(capsys, ["plot", "curves", str(run), "--out", out])


def test_a_torn_last_row_is_dropped_on_resume(run_once, tmp_path):
    run = _damaged_copy(run_once, tmp_path, lambda payload: None)
    rows = (run / "progress.jsonl").read_text()
    (run / "progress.jsonl").write_text(rows + '{"update": 2, "glo')  # killed mid-write
    assert read_rows(run / "progress.jsonl") == [json.loads(rows)]


def test_init_from_a_damaged_value_normaliser_is_one_line(run_once, tmp_path, capsys):
    damage, expected = RUN_STATE_DAMAGE["value normaliser keys"]
    run = _damaged_copy(run_once, tmp_path, damage)
    cfg = tiny_config(tmp_path / "new", init_from=str(run / "checkpoint.pt"))
    with pytest.raises(CheckpointError, match=expected):
        train(cfg, progress=False, stop_after_updates=1)
    assert not Path(cfg.run_dir).exists()


_JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3)
    ),
    max_leaves=8,
)


@settings(max_examples=150, deadline=None)
@given(
    lines=st.lists(
        st.one_of(
            st.binary(max_size=20),
            _JSON_VALUES.map(lambda v: json.dumps(v).encode()),
            st.fixed_dictionaries(
                {"update": _JSON_VALUES, "global_step": st.integers(-2, 2**40)},
                optional={"x": _JSON_VALUES},
            ).map(lambda v: json.dumps(v).encode()),
        ),
        max_size=4,
    )
)
def test_any_progress_file_gives_checked_rows_or_one_line(tmp_path_factory, lines):
    path = tmp_path_factory.mktemp("p") / "progress.jsonl"
    path.write_bytes(b"\n".join(lines))
    try:
        rows = read_rows(path)
    except ProgressError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
        return
    for row in rows:
        assert isinstance(row["update"], int) and isinstance(row["global_step"], int)
        assert all(isinstance(v, (int, float)) or v is None for v in row.values())


# ----------------------------------------------------------------------------- 3: output paths
@pytest.fixture(scope="module")
def demand_results(tmp_path_factory) -> Path:
    """Results of one demand cell (vehicles enter at 3200 veh/h), 3 steps of 1 episode."""
    folder = tmp_path_factory.mktemp("demand")
    grid = folder / "grid.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\ninflow_vph = 3200\ncav_penetration = 0.4\nstyle_mix = "D1"\n'
    )
    out = folder / "out"
    argv = ["eval", "--policy", "pure-hdv", "--grid", str(grid), "--episodes", "1"]
    assert main([*argv, "--episode-steps", "3", "--no-progress", "--out", str(out)]) == 0
    return out


def test_table_reads_demand_results(demand_results, capsys):
    capsys.readouterr()
    assert main(["table", str(demand_results)]) == 0
    assert "| Q=3200 veh/h, rho=0.4, D1 | Speed (m/s) |" in capsys.readouterr().out


def test_table_output_paths_are_checked_before_work(demand_results, tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("keep")
    for out, expected in [
        (tmp_path, "is a folder; give the name of a file"),
        (blocker / "table.md", "is not a folder"),
    ]:
        assert expected in _one_line_error(
            capsys, ["table", str(demand_results), "--out", str(out)]
        )
    # refused before the results are read
    err = _one_line_error(capsys, ["table", str(tmp_path / "missing"), "--out", str(tmp_path)])
    assert "is a folder" in err
    assert blocker.read_text() == "keep"


@pytest.mark.parametrize(
    ("column", "value", "expected"),
    [
        ("n_vehicles", "many", "field 'n_vehicles' is not a number ('many')"),
        ("n_vehicles", "2.5", "field 'n_vehicles' is not a whole number ('2.5')"),
        ("cav_penetration", "0.4x", "field 'cav_penetration' is not a number"),
    ],
)
def test_table_refuses_cell_keys_that_are_not_numbers(tmp_path, capsys, column, value, expected):
    grid = tmp_path / "grid.toml"
    grid.write_text('[[cells]]\nmap = "train-25"\nn_vehicles = 6\ncav_penetration = 0.5\n'
                    'style_mix = "D1"\n')  # fmt: skip
    out = tmp_path / "out"
    argv = ["eval", "--policy", "pure-hdv", "--grid", str(grid), "--episodes", "1"]
    assert main([*argv, "--episode-steps", "3", "--no-progress", "--out", str(out)]) == 0
    episodes = out / "episodes.csv"
    header, row = episodes.read_text().splitlines()[:2]
    fields = row.split(",")
    fields[header.split(",").index(column)] = value
    episodes.write_text(header + "\n" + ",".join(fields) + "\n")
    assert expected in _one_line_error(capsys, ["table", str(out)])


def test_eval_into_an_unusable_cells_folder_is_one_line_before_work(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "cells").write_text("not a folder")
    before = _snapshot(tmp_path)
    argv = ["eval", "--policy", "pure-hdv", "--episodes", "1", "--episode-steps", "3"]
    err = _one_line_error(capsys, [*argv, "--no-progress", "--out", str(out)])
    assert "cannot write into" in err and "cells (not a folder)" in err
    assert _snapshot(tmp_path) == before


def test_a_checkpoint_write_that_fails_is_one_line(run_once, tmp_path):
    """A file-size limit (EFBIG): torch's zip writer raised a RuntimeError, not an OSError."""
    import resource
    import signal

    from diacc.learn.checkpoint import save_checkpoint
    from diacc.learn.mappo import make_agent

    run = _damaged_copy(run_once, tmp_path, lambda payload: None)
    before = (run / "checkpoint.pt").read_bytes()
    cfg = _resume_config(run_once, run)
    agent = make_agent(cfg, torch.device("cpu"))
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
    resource.setrlimit(resource.RLIMIT_FSIZE, (10_000, hard))
    try:
        with pytest.raises(CheckpointError) as info:
            save_checkpoint(run / "checkpoint.pt", agent, cfg, 2, 80)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)
    message = str(info.value)
    assert message.startswith("cannot write checkpoint") and "\n" not in message
    assert "the previous checkpoint is unchanged" in message
    assert (run / "checkpoint.pt").read_bytes() == before
    assert not list(run.glob("*.tmp"))


# ----------------------------------------------------------------------------- 4: Python API
@pytest.fixture(scope="module")
def zoo_env():
    env = diacc.parallel_env(
        scenario={"n_vehicles": 8, "cav_penetration": 0.25}, sim={"episode_steps": 3}
    )
    yield env
    env.close()


@pytest.mark.parametrize(
    ("actions", "error", "expected"),
    [
        (None, TypeError, "step() takes a dict of agent name -> action, got NoneType"),
        ([0, 0], TypeError, "got list"),
        ({"cav_9": 0}, ValueError, "'cav_9', which is not an agent of this env"),
        ({"cav_0": 1.5}, TypeError, "the action of cav_0 is 1.5; actions are whole numbers"),
        ({"cav_0": 7}, ValueError, "the action of cav_0 is 7; actions are 0..4"),
        ({"cav_0": True}, TypeError, "the action of cav_0 is True"),
    ],
)
def test_a_bad_step_is_one_line_and_changes_nothing(zoo_env, actions, error, expected):
    zoo_env.reset(seed=3)
    steps, x_m = zoo_env.steps, zoo_env.state_.x_m.copy()
    with pytest.raises(error) as info:
        zoo_env.step(actions)
    assert isinstance(info.value, DiaccError) and "\n" not in str(info.value)
    assert expected in str(info.value)
    assert zoo_env.steps == steps and np.array_equal(zoo_env.state_.x_m, x_m)


def test_steps_after_the_episode_ended_and_odd_seeds_are_refused(zoo_env):
    for seed, error in [(1.5, TypeError), (-1, ValueError), (2**32, ValueError), ("1", TypeError)]:
        with pytest.raises(error, match=r"reset\(seed=\.\.\.\)"):
            zoo_env.reset(seed=seed)
    zoo_env.reset(seed=np.int64(4))
    while zoo_env.agents:
        zoo_env.step({agent: np.int64(0) for agent in zoo_env.agents})
    steps = zoo_env.steps
    assert zoo_env.step({}) == ({}, {}, {}, {}, {}) and zoo_env.steps == steps  # nobody acts
    with pytest.raises(ValueError, match=r"the episode has ended; call reset\(\) before step\(\)"):
        zoo_env.step({"cav_0": 0})
    with pytest.raises(ValueError, match="the episode has ended"):
        zoo_env.step_arrays(np.zeros(zoo_env.n_cavs, np.int64))
    zoo_env.reset(seed=4)
    with pytest.raises(TypeError, match=r"step_arrays\(\) takes \(2,\) integer actions"):
        zoo_env.step_arrays(np.zeros(zoo_env.n_cavs))


@settings(max_examples=60, deadline=None)
@given(
    actions=st.one_of(
        st.none(),
        st.integers(),
        st.lists(st.integers(-2, 6), max_size=3),
        st.dictionaries(
            st.sampled_from(["cav_0", "cav_1", "cav_7", "x"]),
            st.one_of(
                st.integers(-3, 8), st.floats(allow_nan=True), st.booleans(), st.text(max_size=2)
            ),
            max_size=3,
        ),
    )
)
def test_any_step_argument_steps_or_is_one_line(zoo_env, actions):
    zoo_env.reset(seed=5)
    try:
        zoo_env.step(actions)
    except (ValueError, TypeError) as exc:
        assert isinstance(exc, DiaccError) and "\n" not in str(exc)
        assert zoo_env.steps == 0
    else:
        assert zoo_env.steps == 1


# ----------------------------------------------------------------------------- 5: trust, signals
@pytest.mark.parametrize("planted", ["other-user", "world-writable", "link", None])
def test_the_shared_sumo_cache_fallback_must_be_private(tmp_path, monkeypatch, planted):
    from diacc.sim.backends.base import BackendError
    from diacc.sim.backends.sumo import net

    monkeypatch.setattr(net.tempfile, "gettempdir", lambda: str(tmp_path))
    unusable = tmp_path / "a-file" / "cache"  # a folder under a file: unusable even for root
    (tmp_path / "a-file").write_text("")
    own = tmp_path / f"diacc-{os.getuid()}"
    if planted == "link":
        (tmp_path / "theirs").mkdir()
        own.symlink_to(tmp_path / "theirs")
    elif planted is not None:
        (own / "sumo").mkdir(parents=True)
        (own / "sumo" / "net-0123.net.xml").write_text("<net/>")  # a planted network
        if planted == "world-writable":
            os.chmod(own / "sumo", 0o777)
        elif os.getuid() == 0:
            os.chown(own, 12345, 12345)
        else:
            pytest.skip("only root can give a folder to another user")
    if planted is None:
        assert net.usable_cache(unusable) == own / "sumo"
        assert os.stat(own).st_mode & 0o777 == 0o700
        return
    with pytest.raises(BackendError, match="refused .another user could plant") as info:
        net.usable_cache(unusable)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- 6: smaller
def test_bad_options_are_one_line(capsys):
    for argv, expected in [
        (["simulate", "--seed", "-7"], "argument --seed: must be in [0, 2^32 - 1], got -7"),
        (["simulate", "--seed", "x"], "argument --seed: not a whole number: 'x'"),
        (["simulate", "--bogus"], "unrecognized arguments: --bogus"),
    ]:
        capsys.readouterr()
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and err.count("\n") == 1 and expected in err, err


def test_a_seed_beyond_sumos_signed_range_runs_on_sumo(capsys):
    """SUMO's --seed is a signed 32-bit int: 2^32 - 1 once failed with 3 lines of TraCI."""
    assert main(["simulate", "--backend", "sumo", "--seed", str(2**32 - 1), "--steps", "2"]) == 0


def test_a_config_that_cannot_run_is_one_line_without_the_config_table(tmp_path, capsys):
    capsys.readouterr()
    argv = ["train", "--map", "train-25", "--set", "env.scenario.n_vehicles=300"]
    assert main([*argv, "--run-dir", str(tmp_path / "run")]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "300 vehicles do not fit" in err
    assert not (tmp_path / "run").exists()


def test_a_refused_raw_pickle_gives_no_torch_warning(tmp_path):
    import pickle
    import warnings

    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps(print, protocol=4))  # protocol 4: torch warned of it
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(CheckpointError, match="could run code"):
            load_checkpoint(path)
    assert not caught, [str(w.message) for w in caught]


def test_a_map_name_holding_a_path_stays_out_of_the_run_directory(tmp_path):
    from helpers import SHORT_MAP

    from diacc.config import TrainConfig, default_run_dir

    road = tmp_path / "m.toml"
    road.write_text(SHORT_MAP.replace('name = "short"', 'name = "../../../outside/x"'))
    run_dir = default_run_dir(override(TrainConfig(), {"env.map": str(road)}))
    assert run_dir.startswith("runs/") and ".." not in run_dir and run_dir.count("/") == 1


def test_a_compressed_checkpoint_is_refused_before_it_is_unpacked(run_once, tmp_path):
    """A zip bomb: 1 MB that once took the loader 1.25 GB before it was refused."""
    import zipfile

    bomb = tmp_path / "bomb.pt"
    with zipfile.ZipFile(run_once / "checkpoint.pt") as src, zipfile.ZipFile(bomb, "w") as dst:
        for entry in src.infolist():
            dst.writestr(entry.filename, src.read(entry), compress_type=zipfile.ZIP_DEFLATED)
        dst.writestr("bomb/data/9", bytes(20_000_000), compress_type=zipfile.ZIP_DEFLATED)
    assert bomb.stat().st_size < 1_000_000
    with pytest.raises(CheckpointError, match="holds compressed entries") as info:
        load_checkpoint(bomb)
    assert "\n" not in str(info.value)
