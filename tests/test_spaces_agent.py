"""Spaces every wrapper accepts, episode metrics in ``infos``, render modes, and
:func:`diacc.load_policy` acting on PettingZoo observations."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import diacc
from diacc.envs.env import INFO_METRICS, RenderModeError
from diacc.envs.episode import EpisodeDriver
from diacc.envs.observation import ObservationSpec
from diacc.envs.spaces import SpaceError, unflatten
from diacc.experiments.policies import CheckpointPolicy, PolicyError
from diacc.sim import viewer

SMALL = {"scenario": {"n_vehicles": 8, "cav_penetration": 0.25}}
CHECKPOINT = "checkpoints/diacc-train50-paper-congestion-s1.pt"


def test_masks_are_integer_multibinary_and_state_has_a_space():
    env = diacc.parallel_env(**SMALL)
    try:
        space = env.observation_space("cav_0")
        binaries = {
            k: s for k, s in space.spaces.items() if isinstance(s, gymnasium.spaces.MultiBinary)
        }
        assert set(binaries) == {"hdv_mask", "cav_mask", "lane_mask", "action_mask", "alive"}
        assert all(isinstance(s.n, int) for s in binaries.values())  # TorchRL reads n as an int
        observations, _ = env.reset(seed=0)
        for obs in observations.values():
            assert space.contains(obs)
        state = env.state()
        assert env.state_space.contains(state) and state.shape == env.state_space.shape
    finally:
        env.close()


def test_flat_format_passes_the_api_test_and_unflattens_to_the_dict():
    flat_env = diacc.parallel_env(observation_format="flat", **SMALL)
    dict_env = diacc.parallel_env(**SMALL)
    try:
        parallel_api_test(flat_env, num_cycles=10)
        space = flat_env.observation_space("cav_0")
        assert isinstance(space, gymnasium.spaces.Box) and space.dtype == np.float32
        flat, _ = flat_env.reset(seed=4)
        structured, _ = dict_env.reset(seed=4)
        spec = ObservationSpec.from_config(flat_env.config.obs)
        for agent, vector in flat.items():
            back = unflatten(spec, vector)
            for key, value in structured[agent].items():
                np.testing.assert_array_equal(back[key], value)
        with pytest.raises(SpaceError, match="flat observation has shape"):
            unflatten(spec, vector[:-1])
    finally:
        flat_env.close()
        dict_env.close()


def test_unknown_observation_format_is_a_one_line_error():
    with pytest.raises(SpaceError, match="unknown observation_format 'graph'"):
        diacc.parallel_env(observation_format="graph", **SMALL)


def test_episode_metrics_arrive_with_the_last_agent():
    env = diacc.parallel_env(**{**SMALL, "sim": {"episode_steps": 12}})
    try:
        env.reset(seed=1)
        steps_with_metrics = []
        while env.agents:
            actions = {a: 3 for a in env.agents}  # accelerate
            _, _, _, _, infos = env.step(actions)
            if any("episode_metrics" in info for info in infos.values()):
                steps_with_metrics.append(infos)
        assert len(steps_with_metrics) == 1  # only on the step that ends the episode
        metrics = next(iter(steps_with_metrics[0].values()))["episode_metrics"]
        assert set(metrics) == set(INFO_METRICS)
        assert 0.0 < metrics["mean_speed_mps"] < 40.0
        assert 0.0 <= metrics["p_we"] <= 1.0 and 0.0 <= metrics["p_sce"] <= 1.0
        assert metrics["episode_steps"] <= 12
    finally:
        env.close()


def test_render_follows_render_mode(monkeypatch):
    env = diacc.parallel_env(render_mode="rgb_array", **SMALL)
    try:
        env.reset(seed=0)
        frame = env.render()
        assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    finally:
        env.close()
    plain = diacc.parallel_env(**SMALL)
    try:
        plain.reset(seed=0)
        with pytest.raises(RenderModeError, match="render\\(\\) needs a render_mode"):
            plain.render()
    finally:
        plain.close()
    with pytest.raises(RenderModeError, match="unknown render_mode 'ansi'"):
        diacc.parallel_env(render_mode="ansi", **SMALL)
    monkeypatch.setattr(viewer, "_DISPLAY", False)
    with pytest.raises(RenderModeError, match="needs a display"):
        diacc.parallel_env(render_mode="human", **SMALL)


def test_load_policy_acts_like_the_evaluator_on_pettingzoo_observations():
    """Same checkpoint, same seed: the public API picks the evaluator's actions."""
    policy = diacc.load_policy(CHECKPOINT)
    env = policy.make_env(sim={"episode_steps": 15})
    reference = CheckpointPolicy(CHECKPOINT)
    chosen = []  # the evaluator's actions, (C,) per step
    act = reference.act
    reference.act = lambda obs, first_step: chosen.append(act(obs, first_step)) or chosen[-1]
    driver = EpisodeDriver(reference, env.config)
    try:
        observations, _ = env.reset(seed=2)
        policy.reset(seed=2)
        driver.reset(seed=2)
        while env.agents:
            actions = policy.act(observations)
            driver.step()
            for agent, action in actions.items():
                assert action == chosen[-1][env.possible_agents.index(agent)]
            observations, *_ = env.step(actions)
        assert len(chosen) == 15
        assert policy.act({}) == {} and not policy._hidden  # agents that left are forgotten
    finally:
        env.close()
        driver.close()


def test_load_policy_sampled_is_seeded_and_takes_flat_observations():
    policy = diacc.load_policy(CHECKPOINT, sampled=True)
    env = policy.make_env(observation_format="flat")
    try:
        runs = []
        for _ in range(2):
            observations, _ = env.reset(seed=0)
            policy.reset(seed=5)
            runs.append([policy.act(observations) for _ in range(3)])
        assert runs[0] == runs[1]
        with pytest.raises(SpaceError, match="do not fit checkpoint"):
            policy.act({"cav_0": np.zeros(3, np.float32)})
    finally:
        env.close()


def test_load_policy_refuses_a_baseline_and_a_missing_file():
    with pytest.raises(PolicyError, match="baseline"):
        diacc.load_policy("pure-hdv")
    with pytest.raises(PolicyError, match="does not exist"):
        diacc.load_policy("nowhere/checkpoint.pt")


def test_load_policy_forgets_agents_that_left_and_keeps_the_others():
    policy = diacc.load_policy(CHECKPOINT)
    env = policy.make_env()
    try:
        observations, _ = env.reset(seed=1)
        first, second = env.possible_agents[:2]
        both = {first: observations[first], second: observations[second]}
        policy.reset()
        policy.act(both)
        alone = policy.act({second: observations[second]})  # `first` has left
        assert set(policy._hidden) == {second}
        policy.reset()
        policy.act(both)
        together = policy.act(both)
        assert alone[second] == together[second]  # agents' memories do not mix
    finally:
        env.close()
