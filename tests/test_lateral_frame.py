"""The agents' lateral frame (diacc.envs.lateral_frame): a right-drop road is seen as its mirror."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import first_env

from diacc.config import ConfigError, EnvConfig, ObservationConfig
from diacc.envs.actions import ACCELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.env import BottleneckEnv, decide
from diacc.envs.episode import EpisodeDriver, play_episode
from diacc.envs.lateral_frame import agent_map, is_mirrored, mirror_actions, mirror_state
from diacc.envs.observation import ObservationBuilder
from diacc.experiments.policies import build_policy, parse_policy
from diacc.sim.backends.base import make_backend
from diacc.sim.maps import load_map

LEFT_DROP = load_map("train-50")  # lanes 2 and 3 end at 800 m
RIGHT_DROP = dataclasses.replace(LEFT_DROP, drop_side="right")  # lanes 0 and 1 end there


def _config(frame: str, **env) -> EnvConfig:
    return EnvConfig(obs=ObservationConfig(lateral_frame=frame), **env)


def _env(road, frame: str, **env) -> BottleneckEnv:
    cfg = _config(frame, **env)
    return BottleneckEnv(cfg, backend=make_backend("highway", road, cfg.sim))


def test_only_a_right_drop_road_is_mirrored_and_only_under_drop_left():
    assert is_mirrored(RIGHT_DROP, "drop-left") and not is_mirrored(RIGHT_DROP, "world")
    assert not is_mirrored(LEFT_DROP, "drop-left")
    assert agent_map(RIGHT_DROP, "drop-left").drop_side == "left"
    assert agent_map(LEFT_DROP, "drop-left") is LEFT_DROP
    assert mirror_actions([REMAIN, LANE_LEFT, LANE_RIGHT, ACCELERATE]).tolist() == [
        REMAIN,
        LANE_RIGHT,
        LANE_LEFT,
        ACCELERATE,
    ]
    assert np.array_equal(mirror_actions(mirror_actions(np.arange(5))), np.arange(5))
    with pytest.raises(ConfigError, match="lateral_frame"):
        ObservationConfig(lateral_frame="upside-down")


def test_mirrored_traffic_on_a_right_drop_road_looks_like_the_left_drop_road():
    """The same traffic reflected onto the right-drop road gives the agents exactly the
    observation they get on the left-drop road: the geometry they were trained on."""
    env = _env(LEFT_DROP, "drop-left")
    actor_left, critic_left = env.reset_arrays(seed=3)
    world_right = mirror_state(env.state_, LEFT_DROP)  # the traffic on the right-drop road
    cfg = ObservationConfig()
    builder = ObservationBuilder(RIGHT_DROP, cfg, env.config.sim.episode_steps)
    builder.reset(world_right)
    slots = (env.cav_index[None], env.action_memory[None], env.last_refined[None])  # E = 1
    actor_right = first_env(builder.actor(*slots))
    for name in ("self_state", "hdv_nodes", "cav_nodes", "lane_stats", "lane_mask", "road"):
        assert np.array_equal(getattr(actor_right, name), getattr(actor_left, name)), name
    critic_right = first_env(builder.critic())
    assert np.array_equal(critic_right.nodes, critic_left.nodes)
    assert np.array_equal(critic_right.lane_stats, critic_left.lane_stats)
    # The literal frame sees the world's lanes: lane 0 stays lane 0.
    world = ObservationBuilder(RIGHT_DROP, ObservationConfig(lateral_frame="world"), 100)
    world.reset(world_right)
    raw = first_env(world.actor(*slots))
    lane = world_right.lane[0, env.cav_index] / (LEFT_DROP.max_lanes - 1)
    assert np.allclose(raw.self_state[:, 4], lane)
    assert np.allclose(actor_right.self_state[:, 4], 1 - lane)


def test_actions_cross_the_frame_boundary_swapped_both_ways():
    """On a right-drop road, the agents' "right" (towards the lanes that survive in their
    frame) is the world's left; what PSAR executed comes back in the agents' frame."""
    env = _env(RIGHT_DROP, "drop-left", use_psar=False)
    env.reset_arrays(seed=1)
    state, slots = env.state_, env.cav_index  # a batch of one env, (C,) slots
    lane = state.lane[0, slots]
    movable = (lane < RIGHT_DROP.max_lanes - 1) & (state.segment[0, slots] == 0)
    assert movable.any()
    actions = np.where(movable, LANE_RIGHT, REMAIN)
    decision = first_env(decide(state, slots[None], actions[None], env.config, env.road))
    assert np.array_equal(decision.commands.lane_change[slots], np.where(movable, +1, 0))
    assert np.array_equal(decision.refined, actions) and np.array_equal(decision.proposed, actions)
    literal_cfg = _config("world", use_psar=False)
    literal = first_env(decide(state, slots[None], actions[None], literal_cfg, env.road))
    assert np.all(literal.commands.lane_change[slots][movable & (lane > 0)] == -1)


def test_the_psar_mask_is_in_the_agents_frame():
    road_env = _env(RIGHT_DROP, "drop-left", psar_actions="masked")
    literal_env = _env(RIGHT_DROP, "world", psar_actions="masked")
    mirrored, _ = road_env.reset_arrays(seed=2)
    literal, _ = literal_env.reset_arrays(seed=2)
    assert not np.array_equal(literal.action_mask, literal.action_mask[:, [0, 2, 1, 3, 4]])
    assert np.array_equal(mirrored.action_mask, literal.action_mask[:, [0, 2, 1, 3, 4]])


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_the_heuristic_drives_the_same_episode_in_either_frame(backend, tmp_path):
    """The heuristic reads the map as the agents see it, so its world commands, and the
    episode, are the same whichever frame it acts in: the frame is consistent end to end."""
    path = tmp_path / "right-50.toml"
    path.write_text(
        'name = "right-50"\ndescription = "t"\nlane_width_m = 3.2\ndrop_side = "right"\n'
        + "".join(
            f'[[segments]]\nkind = "{k}"\nlength_m = {n}\nlanes = {lanes}\nspeed_limit_mps = 25.0\n'
            for k, n, lanes in (
                ("multilane", 300, 4),
                ("reduction50", 200, 2),
                ("multilane", 200, 4),
            )
        )
    )
    results = {}
    for frame in ("drop-left", "world"):
        cfg = EnvConfig(backend=backend, map=str(path), obs=ObservationConfig(lateral_frame=frame))
        cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, episode_steps=60))
        driver = EpisodeDriver(build_policy(parse_policy("heuristic")), cfg)
        try:
            recorder = play_episode(driver, seed=4)
            results[frame] = (driver.state.x_m[0].copy(), driver.state.lane[0].copy())
        finally:
            driver.close()
        assert recorder.summary().mean_speed_mps > 0
    assert np.array_equal(results["drop-left"][1], results["world"][1])
    assert np.allclose(results["drop-left"][0], results["world"][0])
