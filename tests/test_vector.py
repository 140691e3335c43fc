"""Vector envs: per-env seeds, in-process == worker processes, crash recovery."""

from __future__ import annotations

import os
import signal

import numpy as np

from diacc.env import EnvConfig
from diacc.scenario import Scenario
from diacc.vector import ProcessVectorEnv, SyncVectorEnv, episode_seed

CONFIG = EnvConfig(scenario=Scenario(n_vehicles=10, cav_penetration=0.3))


def _run(envs, steps: int = 5):
    actor, _ = envs.reset(first_episode=0)
    xs = [actor.self_state.copy()]
    rng = np.random.default_rng(0)
    for _ in range(steps):
        out = envs.step(rng.integers(0, 5, (envs.n_envs, envs.n_cavs)))
        xs.append(out.actor_obs.self_state.copy())
    return np.stack(xs)


def test_episode_seeds_are_distinct_and_reproducible():
    seeds = {episode_seed(1, e, k) for e in range(20) for k in range(50)}
    assert len(seeds) == 1000
    assert episode_seed(1, 2, 3) == episode_seed(1, 2, 3) != episode_seed(2, 2, 3)


def test_process_workers_match_in_process_envs():
    sync = SyncVectorEnv(CONFIG, 2, run_seed=5)
    procs = ProcessVectorEnv(CONFIG, 2, run_seed=5)
    try:
        a, b = _run(sync), _run(procs)
    finally:
        sync.close()
        procs.close()
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a[:, 0], a[:, 1]), "the two envs must get different seeds"


def test_crashed_worker_is_restarted_and_its_episode_cut():
    envs = ProcessVectorEnv(CONFIG, 2, run_seed=5)
    try:
        envs.reset()
        os.kill(envs.workers[1].pid, signal.SIGKILL)
        envs.workers[1].join()
        out = envs.step(np.zeros((2, envs.n_cavs), np.int64))
        assert out.restarts == 1 and envs.restarts == 1
        assert out.terminated[1] and out.reward[1] == 0.0 and not out.alive[1].any()
        assert out.actor_obs.alive[1].all(), "the restarted env starts a fresh episode"
        out = envs.step(np.zeros((2, envs.n_cavs), np.int64))  # and keeps running
        assert out.restarts == 0
    finally:
        envs.close()
    assert all(not w.is_alive() for w in envs.workers)
