"""Fault injection (issue 15): real processes killed by pid, signals, damaged files, bad input.

Each test names the numbered case of issue 15 it covers. Commands run as
``python -m diacc.cli`` subprocesses where the fault needs a live process
tree (``PYTHONPATH`` is inherited, so ``PYTHONPATH=/other/tree pytest
tests/test_faults.py`` checks another checkout's behaviour); the rest run
in this process. Every test is CI-sized (seconds).
"""

from __future__ import annotations

import gzip
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from diacc.cli import main

ENV = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
#: Seconds any one command may take before the test calls it hung.
HANG_S = float(os.environ.get("DIACC_TEST_HANG_S", "180"))

TINY_TOML = """
rollout_steps = 10
# 1-2 envs x 10 steps are 1-2 sequences, fewer than the default 4 minibatches
minibatches = 1
epochs = 2
checkpoint_every = 1
device = "cpu"
[env.sim]
episode_steps = 10
[env.scenario]
n_vehicles = 8
cav_penetration = 0.25
[model]
hidden_dim = 32
gru_hidden = 32
cross_dim = 32
"""
#: Environment steps of one update of TINY_TOML with --envs 2.
STEPS_PER_UPDATE = 20

ROAD_TOML = """
name = "{name}"
lane_width_m = 3.2
[[segments]]
kind = "multilane"
length_m = {length}
lanes = 3
speed_limit_mps = 25.0
"""


# ----------------------------------------------------------------------------- helpers
def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "diacc.cli", *args]


def _descendants(pid: int) -> list[tuple[int, str]]:
    """(pid, command line) of every live descendant of ``pid``, from /proc."""
    parent_of, cmdline = {}, {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if stat.rsplit(")", 1)[1].split()[0] == "Z":  # a zombie is already dead
            continue
        parent_of[int(entry.name)] = int(stat.rsplit(")", 1)[1].split()[1])
        cmdline[int(entry.name)] = cmd
    found, frontier = [], [pid]
    while frontier:
        p = frontier.pop()
        for child, parent in parent_of.items():
            if parent == p:
                found.append((child, cmdline[child]))
                frontier.append(child)
    return found


def _wait_for(predicate, proc: subprocess.Popen, what: str, timeout_s: float = HANG_S):
    """Poll ``predicate`` until it returns something truthy; fail if ``proc`` ends first."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"command ended (rc {proc.returncode}) before {what}: {err[-2000:]}")
        time.sleep(0.05)
    proc.kill()
    pytest.fail(f"timed out waiting for {what}")


def _finish(proc: subprocess.Popen) -> tuple[int, str]:
    """(exit code, stderr) of ``proc``; a command still running after HANG_S is a hang."""
    try:
        _, err = proc.communicate(timeout=HANG_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"command hung (no exit after {HANG_S} s)")
    return proc.returncode, err


def _popen(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        _cli(*args), env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def _rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def _checkpoint_update(run: Path) -> int:
    import torch

    return torch.load(run / "checkpoint.pt", weights_only=True)["update"]


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Input files of the tests: tiny training config, short and broken maps, a grid."""
    root = tmp_path_factory.mktemp("inputs")
    paths = {
        "tiny": root / "tiny.toml",
        "nan_map": root / "nan.toml",
        "inf_map": root / "inf.toml",
        "latin1_map": root / "latin1.toml",
        "grid4": root / "grid4.toml",
        "sumo_grid": root / "sumo_grid.toml",
        "crowded_grid": root / "crowded_grid.toml",
    }
    paths["crowded_grid"].write_text(
        '[[cells]]\nmap = "train-25"\nn_vehicles = 500\ncav_penetration = 0.4\nstyle_mix = "D1"\n'
    )
    paths["tiny"].write_text(TINY_TOML)
    paths["nan_map"].write_text(ROAD_TOML.format(name="nan", length="nan"))
    paths["inf_map"].write_text(ROAD_TOML.format(name="inf", length="inf"))
    paths["latin1_map"].write_bytes(
        ROAD_TOML.format(name="Stra\xdfe", length=100).encode("latin-1")
    )
    paths["grid4"].write_text(
        '[product]\nmap = ["train-25", "train-50"]\nn_vehicles = [25, 40]\n'
        'cav_penetration = [0.4]\nstyle_mix = ["D1"]\n'
    )
    paths["sumo_grid"].write_text(
        '[product]\nmap = ["train-25"]\nn_vehicles = [20, 25]\n'
        'cav_penetration = [0.4]\nstyle_mix = ["D1"]\n'
    )
    return paths


def _train_args(files, run: Path, *extra: str) -> list[str]:
    return [
        "train", "--config", str(files["tiny"]), "--envs", "2", "--steps", "40",
        "--run-dir", str(run), "--no-progress", *extra,
    ]  # fmt: skip


# ----------------------------------------------------------------------------- case 1
def test_case1_eval_pool_worker_killed_retries_its_task(files, tmp_path, capsys):
    """A pool worker killed mid-evaluation: its task is rerun, the restart logged, no hang."""
    out = tmp_path / "pool"
    args = ["eval", "--policy", "pure-hdv", "--grid", str(files["grid4"]), "--episodes", "4"]
    proc = _popen(*args, "--workers", "2", "--out", str(out), "--no-progress")
    _wait_for(lambda: list((out / "cells").glob("*.episodes.csv")), proc, "a finished cell")
    workers = [
        pid
        for pid, cmd in _descendants(proc.pid)
        if "multiprocessing" in cmd and "resource_tracker" not in cmd
    ]
    assert workers, "no pool worker found"
    os.kill(workers[0], signal.SIGKILL)
    code, err = _finish(proc)
    assert code == 0, err
    assert "worker process died" in err
    assert "worker process died" in (out / "eval.log").read_text()
    assert len(list((out / "cells").glob("*.episodes.csv"))) == 4
    # Nothing lost or mixed up: the same results as an unfaulted run.
    assert main([*args, "--workers", "1", "--out", str(tmp_path / "ref"), "--no-progress"]) == 0
    assert (out / "episodes.csv").read_bytes() == (tmp_path / "ref" / "episodes.csv").read_bytes()


# ----------------------------------------------------------------------------- case 2
def test_case2_vector_worker_killed_during_the_update(tmp_path, monkeypatch):
    """A process-vector worker killed while idle (PPO update): replaced, logged, run completes."""
    from test_mappo import tiny_config

    from diacc.learn import mappo, ppo, trainer

    made, killed = [], []
    real_make, real_update = trainer.make_vector_env, ppo.ppo_update

    def make_vector_env(*args, **kwargs):
        made.append(real_make(*args, **kwargs))
        return made[-1]

    def ppo_update(*args, **kwargs):
        if not killed:  # the workers are idle while the learner updates
            worker = made[0].workers[0]
            os.kill(worker.pid, signal.SIGKILL)
            worker.join()
            killed.append(worker.pid)
        return real_update(*args, **kwargs)

    monkeypatch.setattr(trainer, "make_vector_env", make_vector_env)
    monkeypatch.setattr(ppo, "ppo_update", ppo_update)
    cfg = tiny_config(tmp_path, vector="process", checkpoint_every=1)
    run = mappo.train(cfg, progress=False)
    assert killed and _checkpoint_update(run) == 2
    log_text = (run / "train.log").read_text()
    assert f"vector env worker 0 (envs [0], pid {killed[0]})" in log_text
    assert [r["update"] for r in _rows(run / "progress.jsonl")] == [1, 2]


# ----------------------------------------------------------------------------- case 3
def test_case3_nonfinite_gradient_stops_before_the_update(tmp_path, monkeypatch):
    """A NaN gradient in update 2: one-line error naming it; update 1's checkpoint intact."""
    from test_mappo import tiny_config

    from diacc.learn import checkpoint, mappo, trainer

    cfg = tiny_config(tmp_path, checkpoint_every=1, total_steps=80)
    backward_calls = []
    real_make_agent = trainer.make_agent

    def make_agent(cfg_, device):
        agent = real_make_agent(cfg_, device)
        name, param = next(iter(agent.critic.named_parameters()))

        def poison(grad):  # update 2 onwards: the gradient of one critic tensor is NaN
            backward_calls.append(name)  # one backward per minibatch of each epoch
            per_update = cfg.epochs * cfg.minibatches
            return grad * float("nan") if len(backward_calls) > per_update else grad

        param.register_hook(poison)
        return agent

    monkeypatch.setattr(trainer, "make_agent", make_agent)
    with pytest.raises(mappo.TrainingError) as info:
        mappo.train(cfg, progress=False)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"update 2: non-finite gradient of critic.{backward_calls[0]}")
    assert "still holds update 1" in message
    payload = checkpoint.load_checkpoint(tmp_path / "run" / "checkpoint.pt")  # finite, loads
    assert payload["update"] == 1
    assert [r["update"] for r in _rows(tmp_path / "run" / "progress.jsonl")] == [1]


# ----------------------------------------------------------------------------- case 5
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_case5_signal_checkpoints_at_the_update_boundary(files, tmp_path, signum):
    """SIGINT/SIGTERM: the current update finishes and is checkpointed; resume continues it."""
    run = tmp_path / "run"
    args = _train_args(files, run, "--set", "checkpoint_every=1000")
    args[args.index("--steps") + 1] = str(100 * STEPS_PER_UPDATE)
    proc = _popen(*args)
    _wait_for(lambda: _rows(run / "progress.jsonl"), proc, "the first update")
    os.kill(proc.pid, signum)
    code, err = _finish(proc)
    assert code == 128 + signum, err
    assert f"interrupted by {signum.name} after update" in err
    done = _checkpoint_update(run)
    assert [r["update"] for r in _rows(run / "progress.jsonl")] == list(range(1, done + 1))
    assert "checkpoint" in (run / "train.log").read_text()
    if signum != signal.SIGINT:
        return  # resuming is the same after either signal; once is enough
    args[args.index("--steps") + 1] = str((done + 1) * STEPS_PER_UPDATE)
    assert main([*args, "--resume"]) == 0
    assert [r["update"] for r in _rows(run / "progress.jsonl")] == list(range(1, done + 2))


def test_case5_resume_after_a_kill_cuts_progress_and_tensorboard(files, tmp_path):
    """SIGKILL after an unsaved update: resume drops its rows (and TensorBoard events)."""
    run = tmp_path / "run"
    args = _train_args(files, run, "--set", "checkpoint_every=2", "--set", "epochs=6")
    args[args.index("--steps") + 1] = str(100 * STEPS_PER_UPDATE)
    proc = _popen(*args)
    _wait_for(lambda: len(_rows(run / "progress.jsonl")) >= 3, proc, "update 3")
    proc.kill()
    proc.communicate()
    saved, logged = _checkpoint_update(run), len(_rows(run / "progress.jsonl"))
    assert logged > saved, "the kill must land after an unsaved update"
    args[args.index("--steps") + 1] = str((logged + 1) * STEPS_PER_UPDATE)
    assert main([*args, "--resume"]) == 0
    assert [r["update"] for r in _rows(run / "progress.jsonl")] == list(range(1, logged + 2))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tb"))
    events.Reload()
    steps = [e.step for e in events.Scalars("train/policy_loss")]
    assert steps == [STEPS_PER_UPDATE * u for u in range(1, logged + 2)]


# ----------------------------------------------------------------------------- case 6
@pytest.fixture(scope="module")
def trained_run(files, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("trained") / "run"
    assert main(_train_args(files, run, "--steps", str(STEPS_PER_UPDATE))) == 0
    return run


def test_case6_resume_with_changed_config_needs_the_override(files, trained_run, tmp_path):
    """--resume with another seed is refused (see the table) unless --allow-config-change."""
    run = tmp_path / "copy"
    run.mkdir()
    for name in ("checkpoint.pt", "config.json"):
        (run / name).write_bytes((trained_run / name).read_bytes())
    args = _train_args(files, run, "--resume", "--seed", "2", "--allow-config-change")
    assert main(args) == 0
    assert json.loads((run / "config.json").read_text())["seed"] == 2
    assert "changed config fields: seed" in (run / "train.log").read_text()


# ----------------------------------------------------------------------------- case 8
@pytest.mark.parametrize("damage", ["truncate_episodes", "truncate_speeds", "garble_speeds"])
def test_case8_damaged_cell_file_is_reported_and_recomputed(tmp_path, capsys, damage):
    out = tmp_path / "results"
    args = ["eval", "--policy", "pure-hdv", "--episodes", "2", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    good = (out / "episodes.csv").read_bytes()
    cell = sorted((out / "cells").glob("*.episodes.csv"))[0]
    speeds = cell.with_name(cell.name.replace(".episodes.csv", ".speeds.csv.gz"))
    if damage == "truncate_episodes":
        cell.write_bytes(cell.read_bytes()[: len(cell.read_bytes()) // 2])
    elif damage == "truncate_speeds":
        speeds.write_bytes(speeds.read_bytes()[:200])
    else:
        speeds.write_bytes(gzip.compress(b"not,the,columns\n1,2,3\n"))
    capsys.readouterr()
    assert main(args) == 0
    err = capsys.readouterr().err
    assert f"results cell {cell.name.removesuffix('.episodes.csv')}" in err and "damaged" in err
    assert "damaged" in (out / "eval.log").read_text()
    assert (out / "episodes.csv").read_bytes() == good


# ----------------------------------------------------------------------------- case 9
def test_case9_sumo_worker_killed_during_eval_reruns_its_episode(files, tmp_path, capsys):
    """A SUMO worker killed mid-eval costs one episode's rerun (logged), not the command."""
    out = tmp_path / "sumo"
    args = ["eval", "--policy", "pure-hdv", "--backend", "sumo"]
    args += ["--grid", str(files["sumo_grid"]), "--episodes", "8", "--no-progress"]
    proc = _popen(*args, "--out", str(out))

    def sumo_worker():
        return [p for p, cmd in _descendants(proc.pid) if "diacc.sim.backends.sumo.worker" in cmd]

    seen: dict[int, float] = {}

    def kill_a_running_worker() -> bool:  # one that has run for a while: SUMO is stepping
        for pid in sumo_worker():
            if time.monotonic() - seen.setdefault(pid, time.monotonic()) > 0.2:
                try:
                    os.kill(pid, signal.SIGKILL)
                    return True
                except ProcessLookupError:  # its cell just finished
                    pass
        return False

    _wait_for(kill_a_running_worker, proc, "a running SUMO worker to kill")
    code, err = _finish(proc)
    assert code == 0, err
    assert "SUMO worker" in err and "diacc: warning:" in err
    assert "SUMO worker" in (out / "eval.log").read_text()
    assert main([*args, "--out", str(tmp_path / "ref")]) == 0
    assert (out / "episodes.csv").read_bytes() == (tmp_path / "ref" / "episodes.csv").read_bytes()


def test_case9_sumo_worker_dead_at_reset_is_restarted_and_logged(caplog):
    from diacc.config import SimConfig
    from diacc.sim.backends.sumo.backend import SumoBackend
    from diacc.sim.maps import load_map
    from diacc.sim.scenario import Scenario

    backend = SumoBackend(load_map("train-25"), SimConfig())
    scenario = Scenario(n_vehicles=5, cav_penetration=0.0)
    try:
        backend.reset(scenario, 1)
        pid = backend.worker_pid
        os.kill(pid, signal.SIGKILL)
        backend._proc.wait(timeout=10)
        with caplog.at_level("WARNING", logger="diacc"):
            backend.reset(scenario, 2)
        assert backend.worker_pid != pid
    finally:
        backend.close()
    assert f"SUMO worker (pid {pid}" in caplog.text


def test_case9_simulate_into_a_closed_pipe_is_quiet():
    """``diacc simulate | head``: the reader left early; no BrokenPipeError traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)  # the reader is gone before anything is written
    try:
        proc = subprocess.run(
            _cli("simulate", "--episode-steps", "3", "--vehicles", "5"),
            env=ENV,
            stdout=write_end,
            stderr=subprocess.PIPE,
            text=True,
            timeout=HANG_S,
        )
    finally:
        os.close(write_end)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr, proc.stderr


# ----------------------------------------------------------------------------- bad input
LENGTH = "field 'segments[0].length_m' must be a finite number >= 1 m, got"
BAD_INPUT = [
    # case 3: non-finite config values
    (["train", "--set", "value_coef=nan"], "'value_coef' must be a finite number, got nan"),
    (
        ["train", "--set", "env.reward.w_ego=nan"],
        "config key 'env.reward.w_ego' must be a finite number",
    ),
    (["train", "--set", "lr=inf"], "config key 'lr' must be a finite number, got inf"),
    # case 4 and other out-of-range values
    (["train", "--envs", "0"], "config key 'n_envs' must be in [1, 1024], got 0"),
    (["train", "--steps", "0"], "config key 'total_steps' must be >= 1, got 0"),
    (["train", "--set", "gamma=1.5"], "config key 'gamma' must be in [0, 1], got 1.5"),
    (["train", "--set", "lr=-1"], "config key 'lr' must be > 0, got -1.0"),
    (["train", "--set", "rollout_steps=15"], "rollout_steps 15 must be a multiple of chunk_len 10"),
    (["train", "--set", "env.sim.episode_steps=20"], "rollout_steps 10 must be >= env.sim.episode"),
    (["train", "--set", "vector=threads"], "'vector' must be one of auto, sync, batched, process"),
    # case 6: resume with another config
    (["train", "--resume", "--seed", "2"], "was trained with seed 1, not 2; --resume may change"),
    (["train", "--resume", "--map", "train-50"], "trained with env.map 'train-25', not 'train-50'"),
    # case 7: maps
    (["simulate", "--map", "{nan_map}"], "{nan_map}: " + LENGTH + " nan"),
    (["simulate", "--map", "{inf_map}"], "{inf_map}: " + LENGTH + " inf"),
    (["simulate", "--backend", "sumo", "--map", "{inf_map}"], "{inf_map}: " + LENGTH + " inf"),
    (["train", "--map", "{nan_map}"], "{nan_map}: " + LENGTH + " nan"),
    (["simulate", "--map", "{latin1_map}"], "{latin1_map}: not UTF-8 text (byte 0xdf at offset"),
    # case 9: simulate
    (["simulate", "--episode-steps", "-5"], "--episode-steps must be >= 1, got -5"),
    # issue 22: everything validated before anything is written
    (["train", "--set", "env.scenario.n_vehicles=500"], "500 vehicles do not fit in the first seg"),
    (
        ["train", "--resume", "--allow-config-change", "--set", "env.scenario.n_vehicles=500"],
        "500 vehicles do not fit",
    ),
    (["train", "--set", "env.sim.cav=3"], "config key 'env.sim.cav' is a section"),
    (["train", "--set", "env.scenario.cav_penetration=0.05"], "make 0 CAVs; training needs"),
    (["train", "--seed", "-1"], "'seed' must be in [0, 4294967295], got -1"),
    (["train", "--seed", "4294967296"], "'seed' must be in [0, 4294967295], got 4294967296"),
    (["train", "--steps", "10"], "total_steps 10 is less than one update (rollout_steps 10 x n"),
    (["train", "--run-dir", "{tiny}"], "cannot use {tiny} as the train directory (File exists)"),
    (["train", "--resume", "--overwrite"], "--resume continues the run that --overwrite would"),
    (["eval", "--policy", "pure-hdv", "--grid", "{crowded_grid}"], "500 vehicles do not fit"),
]  # fmt: skip


@pytest.mark.parametrize(("argv", "expected"), BAD_INPUT, ids=[" ".join(a) for a, _ in BAD_INPUT])
def test_bad_input_gives_one_line_error(files, trained_run, tmp_path, capsys, argv, expected):
    """Each bad input: exit 2, one ``diacc: error:`` line naming the problem, nothing written."""
    names = {k: str(v) for k, v in files.items()}
    argv = [a.format(**names) for a in argv]
    if argv[0] == "train":
        resume = "--resume" in argv
        run = trained_run if resume else tmp_path / "run"
        before = (run / "config.json").read_bytes() if resume else None
        # Valid, tiny settings first: the entry's own flags override them.
        argv = _train_args(files, run, *argv[1:])
    if argv[0] == "eval":  # results directory: nothing may be written before the check
        out = tmp_path / "out"
        argv = [*argv, "--out", str(out)]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err, err
    assert expected.format(**names) in err
    if argv[0] == "eval":
        assert not out.exists(), "the results directory was written before validation"
    if argv[0] == "train":
        if resume:
            assert (run / "config.json").read_bytes() == before, "resume rewrote config.json"
        else:
            assert not run.exists(), "the run directory was created before validation"


# ----------------------------------------------------------------------------- issue 22
def test_train_refuses_a_directory_holding_a_run(files, trained_run, tmp_path, capsys):
    """Without --resume a finished run was replaced and its progress.jsonl appended to."""
    run = tmp_path / "copy"
    shutil.copytree(trained_run, run)
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    capsys.readouterr()
    assert main(_train_args(files, run, "--steps", str(STEPS_PER_UPDATE))) == 2
    err = capsys.readouterr().err.strip()
    assert "already holds a run (checkpoint.pt, progress.jsonl, config.json)" in err, err
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    assert main(_train_args(files, run, "--steps", str(STEPS_PER_UPDATE), "--overwrite")) == 0
    assert [r["update"] for r in _rows(run / "progress.jsonl")] == [1]


def test_two_writers_cannot_share_a_run_directory(files, tmp_path, capsys):
    """A second process on a locked run directory gets one line; a stale lock is taken over."""
    from diacc.runlog import LOCK_FILE, locked_dir

    run = tmp_path / "run"
    args = _train_args(files, run, "--steps", str(STEPS_PER_UPDATE))
    with locked_dir(run, "train"):  # as another process holding it would
        holder = subprocess.run(_cli(*args), env=ENV, capture_output=True, text=True)
    assert holder.returncode == 2
    assert f"is in use by another diacc train (process {os.getpid()})" in holder.stderr
    assert not run.exists(), "the refused command left files"
    run.mkdir()
    (run / LOCK_FILE).write_text("999999999\n")  # left by a killed run: nobody holds it
    assert main(args) == 0
    assert not (run / LOCK_FILE).exists()


def test_sweep_compares_the_config_of_a_run_it_would_skip(tmp_path, capsys):
    """A finished run with other settings was skipped and reported under the new ones."""
    from test_sweep_cli import SMALL

    argv = ["sweep", "--variants", "mappo", "--seeds", "1", "--steps", "10", "--envs", "1"]
    argv += ["--out-dir", str(tmp_path), *SMALL]
    assert main(argv) == 0
    capsys.readouterr()
    assert main([*argv, "--set", "epochs=2"]) == 2
    err = capsys.readouterr().err.strip()
    assert "was trained with another epochs than this command asks for" in err, err


def test_sigterm_to_train_with_process_envs_ends_every_child(files, tmp_path):
    """SIGTERM to ``train --set vector=process``: checkpoint, exit 143, no worker left (by pid)."""
    run = tmp_path / "run"
    steps = str(STEPS_PER_UPDATE * 200)
    proc = _popen(*_train_args(files, run, "--steps", steps, "--set", "vector=process"))
    children = _wait_for(
        lambda: [pid for pid, cmd in _descendants(proc.pid) if "resource_tracker" not in cmd][1:],
        proc,
        "the vector-env workers",
    )
    _wait_for(lambda: (run / "progress.jsonl").exists(), proc, "the first update")
    proc.send_signal(signal.SIGTERM)
    code, err = _finish(proc)
    assert code == 128 + signal.SIGTERM, err
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and set(children) & _live_pids():
        time.sleep(0.1)
    assert not set(children) & _live_pids(), "vector-env workers outlived train"


def _live_pids() -> set[int]:
    """Pids of every process that is not a zombie."""
    live = set()
    for entry in Path("/proc").iterdir():
        try:
            if entry.name.isdigit() and (entry / "stat").read_text().rsplit(")", 1)[1][1] != "Z":
                live.add(int(entry.name))
        except OSError:
            continue
    return live


def _die_once(task: tuple[str, str]) -> str:
    """Pool task: ``("die", marker)`` kills its worker the first time (no marker file
    yet), like a SIGKILL, after a short delay; any other task returns its name."""
    name, marker = task
    if name == "die" and not Path(marker).exists():
        Path(marker).touch()
        time.sleep(0.3)
        os._exit(1)
    return name


def test_a_worker_that_dies_between_results_breaks_the_next_submit_not_the_run(tmp_path):
    """The pool can break after one result was taken and before the next task is
    submitted (the consumer is busy meanwhile): that task is resubmitted to a new pool,
    not lost in a BrokenProcessPool traceback (CI caught it on test_case1 above)."""
    from diacc.experiments.workpool import map_resilient

    marker = str(tmp_path / "died")
    tasks = [("a", marker), ("die", marker), ("b", marker), ("c", marker)]
    results = {}
    for i, result in map_resilient(_die_once, tasks, workers=2):
        results[i] = result
        if i == 0:
            time.sleep(1.5)  # the worker of task 1 dies while the consumer holds task 0
    assert results == {0: "a", 1: "die", 2: "b", 3: "c"}
