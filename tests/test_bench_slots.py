"""``diacc bench --agent-slots``: a cap against every CAV an agent, at a tiny size (a
160 m road, 2 envs x 30 steps, tiny networks; seconds)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import SHORT_MAP

from diacc.envs.observation.layout import ObservationSpec
from diacc.envs.vector import make_vector_env
from diacc.experiments.bench import slots
from diacc.learn import ppo
from diacc.learn.agent import make_agent


@pytest.fixture
def tiny(tmp_path) -> dict:
    """20 vehicles over 20 s, half CAVs (10 slots with every CAV), critic rows for 24."""
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    return {
        "env.map": str(road), "env.scenario.kind": "demand", "env.scenario.inflow_vph": 3600.0,
        "env.scenario.demand_s": 20.0, "env.scenario.cav_penetration": 0.5,
        "env.sim.episode_steps": 30, "env.obs.max_vehicles": 24, "chunk_len": 10, "epochs": 1,
        "model.hidden_dim": 32, "model.gru_hidden": 32, "model.cross_dim": 32,
    }  # fmt: skip


def test_the_row_measures_both_settings_and_compares_them(tiny, capsys):
    rows, ratios = slots.run(tiny, n_envs=2, steps=30, cap=3, repeats=1)
    capped, every = rows
    assert (capped["slots"], capped["C"]) == (3, 3)
    assert (every["slots"], every["C"]) == ("every", 10)
    for row in rows:
        for key in ("decisions", "rollout_s", "rollout_cpu_s", "update_s", "update_cpu_s"):
            assert row[key] > 0, key
        assert row["most_on_road"] <= row["C"] and row["decisions"] <= 2 * 30 * row["C"]
    assert every["decisions"] > capped["decisions"]  # the cap leaves CAVs to drive themselves
    assert set(ratios) == set(slots.RATIO_KEYS)
    for key, ratio in ratios.items():
        assert math.isclose(ratio, every[key] / capped[key]), key
    assert math.isclose(ratios["slot_steps_B"], 10 / 3)  # same bytes per slot-step
    out = capsys.readouterr().out
    assert f"x{ratios['rollout_cpu_s']:.2f}" in out and f"x{ratios['decisions']:.2f}" in out


def test_the_bytes_are_the_rollouts_own(tiny):
    """The per-slot, per-row and per-env figures add up to every stored array's bytes,
    and the observations' shares are the layout's (ObservationSpec)."""
    cfg = slots.config("every", tiny, 2, 30, "cpu")
    agent = make_agent(cfg, torch.device("cpu"))
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed, cfg.vector)
    try:
        roll, _, _ = ppo.collect_rollout(agent, envs, cfg, 0, 0, values=False)
    finally:
        envs.close()
    got = slots.buffer_bytes(roll)
    S, E, C = roll.alive.shape
    N = cfg.env.obs.max_vehicles
    stored = [*roll.actor_obs, *roll.critic_state]
    total = sum(a.nbytes for record in stored for a in vars(record).values())
    total += sum(a.nbytes for a in vars(roll).values() if isinstance(a, np.ndarray))
    assert got["total_B"] == total
    assert math.isclose(
        got["slot_B"] * S * E * C + got["critic_row_B"] * S * E * N + got["env_B"] * S * E, total
    )
    spec = ObservationSpec.from_config(cfg.env.obs)
    per_slot = sum(math.prod(s) * d.itemsize for s, d in spec.actor_shapes(1).values())
    assert got["slot_obs_B"] == per_slot
    critic = spec.critic_shapes()
    per_row = sum(math.prod(s) * d.itemsize for s, d in critic.values() if s[0] == N) / N
    assert got["critic_row_B"] == per_row
    # the actor's hidden state is part of each slot's arrays
    assert got["slot_arrays_B"] > cfg.model.gru_hidden * 4
    assert got["slot_steps_B"] == got["slot_B"] * S * E * C
