"""PSAR, reward, safety events and observations of a batch equal those of each env alone.

The vector env test (``tests/test_vector.py``) checks the whole batched step;
these pin a difference down to the module that makes it.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from diacc.config import EnvConfig, resolve_road
from diacc.envs.observation import ObservationBuilder
from diacc.envs.psar import psar
from diacc.envs.reward import reward_terms, team_reward
from diacc.envs.safety import safety_critical_events
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.scenario import Scenario
from diacc.sim.state import TrafficState

N_ENVS, N_VEHICLES, N_CAVS = 3, 25, 10


def assert_fields_equal(batch, singles) -> None:
    """Env ``e`` of ``batch`` equals the E = 1 batch ``singles[e]``."""
    for e, single in enumerate(singles):
        for f in fields(single):
            a, b = getattr(single, f.name)[0], getattr(batch, f.name)[e]
            assert np.array_equal(a, b) and np.asarray(a).dtype == np.asarray(b).dtype, (e, f.name)


@pytest.fixture(scope="module")
def episode():
    """States of N_ENVS envs over 12 random steps, their builders and CAV slots."""
    config = EnvConfig()
    road = resolve_road(config)
    batch = HighwayBackend(road, config.sim, n_envs=N_ENVS)
    scenario = Scenario.with_cavs(N_VEHICLES, N_CAVS)
    states = [batch.reset(scenario, 100 + e, env=e).env(0) for e in range(N_ENVS)]
    builders = [ObservationBuilder(road, config.obs, config.sim.episode_steps) for _ in states]
    for b, s in zip(builders, states, strict=True):
        b.reset(s)
    rng = np.random.default_rng(3)
    history = [states]
    for _ in range(12):
        lane = rng.integers(-1, 2, (N_ENVS, N_VEHICLES)).astype(np.int8)
        stepped = batch.step(CavCommands(lane, rng.normal(0, 2, (N_ENVS, N_VEHICLES))))
        states = [stepped.env(e) for e in range(N_ENVS)]
        for b, s in zip(builders, states, strict=True):
            b.push(s)
        history.append(states)
    cav_index = np.stack([np.flatnonzero(s.is_cav[0]) for s in states])  # (E, C)
    return config, road, history, builders, cav_index


def test_psar_reward_and_events_of_a_batch(episode):
    config, road, history, _, cav_index = episode
    rng = np.random.default_rng(4)
    for states in history:
        batch = TrafficState.concat(states)
        actions = rng.integers(0, 5, cav_index.shape)
        singles = [
            psar(s, c[None], a[None], config.psar, road, config.sim)
            for s, c, a in zip(states, cav_index, actions, strict=True)
        ]
        assert_fields_equal(psar(batch, cav_index, actions, config.psar, road, config.sim), singles)
        singles = [
            reward_terms(s, c[None], road, config.reward)
            for s, c in zip(states, cav_index, strict=True)
        ]
        terms = reward_terms(batch, cav_index, road, config.reward)
        assert_fields_equal(terms, singles)
        parts = ("ego", "alive", "global_reward", "completion", "delay")
        team = team_reward(*(getattr(terms, p) for p in parts), 0.3, config.reward)
        singles = [
            team_reward(*(getattr(t, p) for p in parts), 0.3, config.reward) for t in singles
        ]
        assert_fields_equal(team, singles)
        events = safety_critical_events(batch, config.events)
        singles = [safety_critical_events(s, config.events) for s in states]
        assert_fields_equal(events, singles)
        for e, s in enumerate(states):  # the batch's states are the envs' states
            single = batch.env(e)
            for f in fields(TrafficState):
                assert np.array_equal(getattr(single, f.name), getattr(s, f.name)), f.name


def test_observations_of_a_batch(episode):
    """One builder fed the batch's states gives each env's observations; so do a
    subset of its rows, and a row restarted on a new episode."""
    config, road, history, builders, cav_index = episode
    rng = np.random.default_rng(5)
    memory = rng.integers(0, 5, cav_index.shape + (2,))  # (E, C, 2)
    last = rng.integers(0, 5, (N_ENVS, N_VEHICLES))  # (E, V)
    batched = ObservationBuilder(road, config.obs, config.sim.episode_steps)
    batched.reset(TrafficState.concat(history[0]))
    for states in history[1:]:
        batched.push(TrafficState.concat(states))

    args = (cav_index, memory, last)

    def assert_rows_equal(actor, critic, rows, singles) -> None:
        for k, (e, b) in enumerate(zip(rows, singles, strict=True)):
            for got, single in (
                (actor.unbatched(k), b.actor(*(a[e : e + 1] for a in args)).unbatched(0)),
                (critic.unbatched(k), b.critic().unbatched(0)),
            ):
                for f in fields(single):
                    a, c = getattr(single, f.name), getattr(got, f.name)
                    assert a.dtype == c.dtype and np.array_equal(a, c), (e, f.name)

    actor, critic = batched.actor(cav_index, memory, last), batched.critic()
    assert_rows_equal(actor, critic, range(N_ENVS), builders)
    rows = np.array([0, 2])
    actor, critic = batched.observe_rows(rows, cav_index[rows], memory[rows], last[rows])
    assert_rows_equal(actor, critic, rows, [builders[0], builders[2]])
    # Env 1 starts a new episode: its history is its first state again, the others keep theirs.
    fresh = ObservationBuilder(road, config.obs, config.sim.episode_steps)
    fresh.reset(history[0][0])
    state = TrafficState.concat(history[-1])
    state.set_rows(np.array([1]), history[0][0])
    batched.reset_rows(np.array([1]), state)
    actor, critic = batched.actor(cav_index, memory, last), batched.critic()
    assert_rows_equal(actor, critic, range(N_ENVS), [builders[0], fresh, builders[2]])
