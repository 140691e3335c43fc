"""Vector envs: per-env seeds, in-process == batched == worker processes, crash recovery."""

from __future__ import annotations

import dataclasses
import os
import re
import signal

import numpy as np
import pytest

from diacc.config import SimConfig, resolve_road
from diacc.envs.env import BottleneckEnv, EnvConfig
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.step import VectorStep
from diacc.envs.vector import (
    BatchedVectorEnv,
    SyncVectorEnv,
    auto_vector_mode,
    episode_seed,
    make_vector_env,
    maps_of_envs,
)
from diacc.envs.vector_process import ProcessVectorEnv
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

CONFIG = EnvConfig(scenario=Scenario(n_vehicles=10, cav_penetration=0.3))


def _run(envs, steps: int = 5, outs: list | None = None):
    actor, _ = envs.reset(first_episode=0)
    xs = [actor.self_state.copy()]
    rng = np.random.default_rng(0)
    for _ in range(steps):
        out = envs.step(rng.integers(0, 5, (envs.n_envs, envs.n_cavs)))
        xs.append(out.actor_obs.self_state.copy())
        if outs is not None:
            outs.append(out)
    return np.stack(xs)


def test_episode_seeds_are_distinct_and_reproducible():
    seeds = {episode_seed(1, e, k) for e in range(20) for k in range(50)}
    assert len(seeds) == 1000
    assert episode_seed(1, 2, 3) == episode_seed(1, 2, 3) != episode_seed(2, 2, 3)


def _assert_same_run(sync, procs):
    """Run both vector envs alike (closing them) and assert identical steps; returns
    the in-process run's array."""
    in_process, in_workers = [], []
    try:
        a, b = _run(sync, outs=in_process), _run(procs, outs=in_workers)
    finally:
        sync.close()
        procs.close()
    np.testing.assert_array_equal(a, b)
    assert_same(in_process, in_workers, "steps")
    return a


def test_process_workers_match_in_process_envs():
    sync = SyncVectorEnv(CONFIG, 2, run_seed=5)
    procs = ProcessVectorEnv(SyncVectorEnv, CONFIG, 2, run_seed=5)
    a = _assert_same_run(sync, procs)  # reward terms and episodes included
    assert not np.array_equal(a[:, 0], a[:, 1]), "the two envs must get different seeds"


def assert_same(a, b, where: str) -> None:
    """Exact equality of nested step results (dataclasses, dicts, lists, arrays)."""
    if dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            assert_same(a[key], b[key], f"{where}[{key}]")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and np.array_equal(a, b), where
    else:
        assert a == b or (a != a and b != b), where  # NaN metrics of empty episodes


@pytest.mark.parametrize(
    ("map_name", "n_vehicles", "use_psar"),
    [("train-25", 25, True), ("train-25", 25, False), ("test-50", 40, True)],
)
def test_batched_simulator_matches_envs_stepped_alone(map_name, n_vehicles, use_psar):
    """Same seeds and actions: every field of every step is identical, through
    collisions, time limits and the automatic resets that follow."""
    config = EnvConfig(
        map=map_name,
        scenario=Scenario(n_vehicles=n_vehicles),
        sim=SimConfig(episode_steps=25),
        use_psar=use_psar,
    )
    n_envs, steps = 4, 80
    alone = [SyncVectorEnv(config, n_envs, 7, env_indices=[e]) for e in range(n_envs)]
    sync, batched = SyncVectorEnv(config, n_envs, run_seed=7), BatchedVectorEnv(config, n_envs, 7)
    try:
        first = [env.reset(first_episode=0) for env in alone]
        first = tuple(
            kind.concat([pair[i] for pair in first])
            for i, kind in enumerate((ActorObs, CriticState))
        )
        assert_same(first, batched.reset(first_episode=0), "reset")
        assert_same(first, sync.reset(first_episode=0), "reset")
        rng = np.random.default_rng(1)
        ended = collided = 0
        for t in range(steps):
            actions = rng.integers(0, 5, (n_envs, batched.n_cavs))
            a = VectorStep.concat([env.step(actions[e : e + 1]) for e, env in enumerate(alone)])
            a = dataclasses.replace(a, team=None)
            # The team rewards: tests/test_reward.py (here each env alone counts its own steps).
            for vector in (batched, sync):
                assert_same(a, dataclasses.replace(vector.step(actions), team=None), f"step {t}")
            ended += int((a.terminated | a.truncated).sum())
            collided += sum(e["collision"] for e in a.episodes.values())
    finally:
        for env in (*alone, sync, batched):
            env.close()
    # Resets were compared, and without PSAR's filter collisions too.
    assert ended >= 2 * n_envs and (use_psar or collided >= 1)


def test_maps_of_envs_are_contiguous_blocks():
    assert maps_of_envs(("a",), 3) == ["a", "a", "a"]
    assert maps_of_envs(("a", "b"), 5) == ["a", "a", "a", "b", "b"]
    # A repeated map: another share, still one contiguous block per map.
    assert maps_of_envs(("a", "b", "a"), 6) == ["a", "a", "a", "a", "b", "b"]
    assert maps_of_envs(("a", "a", "a", "b"), 8) == ["a"] * 6 + ["b"] * 2
    with pytest.raises(ValueError, match="2 maps need at least as many envs"):
        maps_of_envs(("a", "b"), 1)


def test_envs_on_several_maps_match_per_env_envs_and_single_map_runs():
    """Two maps, three envs: the batched groups give every field of every step
    as per-env envs do, and each env as a run on its map alone (same seeds)."""
    config = EnvConfig(
        map="train-50", scenario=Scenario(n_vehicles=12), sim=SimConfig(episode_steps=20)
    )
    n_envs, steps = 3, 45
    grouped = make_vector_env(config, n_envs, 3, "batched", extra_maps=("test-25",))
    alone = make_vector_env(config, n_envs, 3, "sync", extra_maps=("test-25",))
    singles = {
        m: SyncVectorEnv(dataclasses.replace(config, map=m), n_envs, 3)
        for m in ("train-50", "test-25")
    }
    assert isinstance(grouped, BatchedVectorEnv)
    roads = [batch.road.name for batch, members in grouped.groups for _ in members]
    assert roads == ["train-50", "train-50", "test-25"]
    try:
        assert_same(grouped.reset(first_episode=0), alone.reset(first_episode=0), "reset")
        for env in singles.values():
            env.reset(first_episode=0)
        rng = np.random.default_rng(2)
        ended = 0
        for t in range(steps):
            actions = rng.integers(0, 5, (n_envs, grouped.n_cavs))
            a, b = grouped.step(actions), alone.step(actions)
            assert_same(a, b, f"step {t}")
            ended += int((a.terminated | a.truncated).sum())
            one = {m: env.step(actions) for m, env in singles.items()}
            for e, m in enumerate(["train-50", "train-50", "test-25"]):
                np.testing.assert_array_equal(
                    a.actor_obs.self_state[e], one[m].actor_obs.self_state[e]
                )
    finally:
        for env in (grouped, alone, *singles.values()):
            env.close()
    assert ended >= n_envs  # automatic resets compared too


@pytest.mark.parametrize("vector", [SyncVectorEnv, BatchedVectorEnv])
def test_every_layer_drives_the_road_resolve_road_gives(vector):
    """The map is resolved in one place (issue 59): the env, each map's batch and its
    episode metrics drive ``resolve_road`` of their config, the preset's limits included."""
    cfg = dataclasses.replace(
        CONFIG, map="train-50", sim=SimConfig(style_preset="paper-congestion")
    )
    road, other = resolve_road(cfg), resolve_road(dataclasses.replace(cfg, map="train-25"))
    assert road != load_map("train-50")  # the preset lowers the reduction's speed limit
    env = BottleneckEnv(cfg)
    envs = vector(cfg, 3, run_seed=0, env_maps=["train-50", "train-50", "train-25"])
    try:
        assert env.road == env.batch.road == road
        assert [batch.road for batch, _ in envs.groups] == [road, other]
        assert [recorder.road for recorder in envs.recorders] == [road, other]
    finally:
        env.close()
        envs.close()


def test_auto_mode_batches_highway_only():
    envs = make_vector_env(CONFIG, 2, run_seed=1)
    try:
        assert isinstance(envs, BatchedVectorEnv)
    finally:
        envs.close()
    lone = make_vector_env(CONFIG, 1, run_seed=1)  # nothing to batch: stepped on its own
    try:
        assert type(lone) is SyncVectorEnv
    finally:
        lone.close()
    with pytest.raises(ValueError, match="highway"):
        BatchedVectorEnv(EnvConfig(backend="sumo"), 2, run_seed=1)


def test_crashed_worker_is_restarted_and_its_episode_cut():
    envs = ProcessVectorEnv(SyncVectorEnv, CONFIG, 2, run_seed=5)
    try:
        envs.reset()
        os.kill(envs.workers[1].pid, signal.SIGKILL)
        envs.workers[1].join()
        out = envs.step(np.zeros((2, envs.n_cavs), np.int64))
        assert out.restarts == 1 and envs.restarts == 1
        # A crash is a truncation, bootstrapped from the last state before it.
        assert out.truncated[1] and not out.terminated[1] and out.crashed.tolist() == [0, 1]
        assert not out.ego[1].any() and out.global_reward[1] == out.completion[1] == 0.0
        assert out.final_critic_state[1] is not None and not out.alive[1].any()
        assert out.actor_obs.alive[1].all(), "the restarted env starts a fresh episode"
        out = envs.step(np.zeros((2, envs.n_cavs), np.int64))  # and keeps running
        assert out.restarts == 0
    finally:
        envs.close()
    assert all(not w.is_alive() for w in envs.workers)


def test_sumo_crash_inside_a_rollout_is_a_truncation():
    """A SUMO worker killed mid-episode: the step is cut, not terminated, and the
    trainer gets the last state before the crash to bootstrap from."""
    envs = SyncVectorEnv(EnvConfig(backend="sumo", scenario=CONFIG.scenario), 1, run_seed=3)
    try:
        envs.reset()
        before = envs.step(np.zeros((1, envs.n_cavs), np.int64))
        os.kill(envs.groups[0][0].sims.backends[0].worker_pid, signal.SIGKILL)
        out = envs.step(np.zeros((1, envs.n_cavs), np.int64))
        assert out.restarts == 1
        assert out.truncated[0] and not out.terminated[0] and out.crashed[0]
        assert not out.ego[0].any() and out.global_reward[0] == out.completion[0] == 0.0
        final = out.final_critic_state[0]
        np.testing.assert_array_equal(final.nodes, before.critic_state.nodes[0])
        out = envs.step(np.zeros((1, envs.n_cavs), np.int64))  # the next episode runs
        assert out.restarts == 0
    finally:
        envs.close()


def test_a_crashed_simulator_cuts_only_its_own_env(caplog):
    """Two SUMO envs stepped as one batch: the one whose simulator dies is cut and
    restarted (the log says which env and why), the other steps on as if alone."""
    config = EnvConfig(backend="sumo", scenario=CONFIG.scenario)
    envs, alone = SyncVectorEnv(config, 2, run_seed=3), SyncVectorEnv(config, 2, 3, [0])
    actions = np.zeros((2, envs.n_cavs), np.int64)
    try:
        envs.reset()
        alone.reset()
        envs.step(actions)
        alone.step(actions[:1])
        os.kill(envs.groups[0][0].sims.backends[1].worker_pid, signal.SIGKILL)
        out, one = envs.step(actions), alone.step(actions[:1])
        assert out.restarts == 1 and out.crashed.tolist() == [False, True]
        # found dead when the step is sent or when its reply is awaited: either names it
        assert re.search(r"env 1: SUMO worker (died|is not running) while stepping", caplog.text)
        assert out.truncated[1] and not out.alive[1].any() and 1 not in out.episodes
        np.testing.assert_array_equal(out.actor_obs.self_state[0], one.actor_obs.self_state[0])
        assert out.global_reward[0] == one.global_reward[0]
        assert len(out.reward_terms["global"]) == 1  # the cut env's step logged nothing
    finally:
        envs.close()
        alone.close()


def test_env_batch_bench_reports_both_paths():
    from diacc.experiments.bench import envbatch

    (row,) = envbatch.run(envs=(2,), steps=2)
    assert row["envs"] == 2
    for key in ("env_sync", "env_batched", "sim_sync", "sim_batched"):
        assert row[f"{key}_steps_per_s"] > 0.0


def test_step_before_after_times_two_trees():
    """benchmarks/speed/step_before_after.py runs each tree in its own process and prints the
    ratio (here the same tree twice)."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, str(root / "benchmarks" / "speed" / "step_before_after.py"),
         str(root), str(root),
         "--envs", "2", "--timing-steps", "2", "--rounds", "1"],
        check=True, capture_output=True, text=True,
    )  # fmt: skip
    assert "round 1: before" in out.stdout and "median: before" in out.stdout


def test_step_identity_finds_a_tree_identical_to_itself_and_settings_apart():
    """benchmarks/speed/step_identity.py: the same seeds give the same digest in two processes
    (the step is deterministic), and two settings give different digests."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    script = str(root / "benchmarks" / "speed" / "step_identity.py")
    out = subprocess.run(
        [sys.executable, script, str(root), str(root), "--only", "nopsar", "masked"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    assert "IDENTICAL" in out.stdout
    digests = dict(line.split()[:2] for line in out.stdout.splitlines()[:2])
    assert digests["nopsar"] != digests["masked"]


def test_auto_mode_spreads_envs_over_workers_when_the_learner_is_on_a_gpu(monkeypatch):
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    assert auto_vector_mode("highway", 16) == "batched"
    assert auto_vector_mode("highway", 1) == "sync"
    assert auto_vector_mode("sumo", 4) == "process"
    assert auto_vector_mode("highway", 16, "cuda") == "process"
    assert auto_vector_mode("highway", 1, "cuda") == "sync"  # nothing to spread
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    assert auto_vector_mode("highway", 16, "cuda") == "batched"  # no second core


def test_process_workers_batch_their_highway_groups(monkeypatch):
    """4 envs on 2 workers: each steps its 2 envs as one batch, with the results of 4
    envs stepped one by one in this process."""
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    sync = SyncVectorEnv(CONFIG, 4, run_seed=5)
    procs = make_vector_env(CONFIG, 4, 5, "auto", learner_device="cuda")
    assert isinstance(procs, ProcessVectorEnv) and procs.group_class is BatchedVectorEnv
    assert procs.groups == [[0, 1], [2, 3]]
    _assert_same_run(sync, procs)
