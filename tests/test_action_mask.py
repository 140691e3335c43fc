"""PSAR-aware action masks (diacc.envs.action_mask) and the ``env.psar_actions`` option."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import make_state

from diacc.config import ConfigError, EnvConfig, TrainConfig, validate
from diacc.envs.action_mask import masked_logits, psar_action_mask
from diacc.envs.actions import ACCELERATE, DECELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.sim.maps import load_map
from diacc.sim.state import TrafficState

ROAD = load_map("train-25")  # 4 lanes at x = 100 m
CFG = EnvConfig(psar_actions="masked")
STOPPING_CFG = dataclasses.replace(CFG, psar=dataclasses.replace(CFG.psar, horizon="stopping"))


def mask_of(
    others: list[tuple[float, int, float]], ego_lane: int = 1, cfg: EnvConfig = CFG, **kw
) -> list[bool]:
    """Mask of CAV 0 at (100 m, ego_lane, 20 m/s) among (x, lane, speed) HDVs."""
    state = make_state(
        [100.0] + [o[0] for o in others],
        [ego_lane] + [o[1] for o in others],
        [20.0] + [o[2] for o in others],
        is_cav=[True] + [False] * len(others),
        **kw,
    )
    return psar_action_mask(TrafficState.concat([state]), np.array([[0]]), cfg, ROAD)[0, 0].tolist()


def allowed(*actions: int) -> list[bool]:
    return [a in actions for a in range(5)]


def test_free_road_allows_everything_the_road_allows():
    assert mask_of([]) == allowed(REMAIN, LANE_LEFT, LANE_RIGHT, ACCELERATE, DECELERATE)
    # Lane 0 has no lane to its right: "right" would become "remain".
    assert mask_of([], ego_lane=0) == allowed(REMAIN, LANE_LEFT, ACCELERATE, DECELERATE)


def test_closing_leader_leaves_only_braking():
    # Gap 7 m closing at 1 m/s: Force-Brake turns remain and accelerate into decelerate;
    # under "stopping" lane changes stay (free neighbour lanes); under "headway" a CAV
    # that must brake for its leader does not change lanes (it is behind that leader
    # during the change), so only braking is left.
    closing = [(112.0, 1, 19.0)]
    assert mask_of(closing, cfg=STOPPING_CFG) == allowed(LANE_LEFT, LANE_RIGHT, DECELERATE)
    assert mask_of(closing) == allowed(DECELERATE)


def test_suppressed_actions_are_masked_and_mask_is_never_empty():
    # Gap 4 m at 20 m/s, opening: inside the gap the CAV needs to stop, so the
    # stopping horizon brakes even though it is not closing (remain and accelerate
    # become decelerate). Lane-change targets blocked by vehicles alongside: only
    # braking is left, never nothing.
    blocked = [(109.0, 1, 21.0), (100.5, 0, 20.0), (100.5, 2, 20.0)]
    assert mask_of(blocked, cfg=STOPPING_CFG) == allowed(DECELERATE)
    # The default "headway" horizon as well: 4 m is less than 2 m + about 1 s at 20 m/s.
    assert mask_of(blocked) == allowed(DECELERATE)


def test_cav_off_the_road_allows_everything():
    assert mask_of([(112.0, 1, 19.0)], active=[False, True]) == [True] * 5


def test_batch_of_states_matches_one_state_at_a_time():
    cav = [True, False, True]
    states = [
        make_state([100.0, 112.0, 300.0], [1, 1, 2], [20.0, 19.0, 20.0], is_cav=cav),
        make_state([100.0, 109.0, 300.0], [0, 0, 3], [20.0, 21.0, 20.0], is_cav=cav),
    ]
    cavs = np.array([[0, 2], [0, 2]])
    batch = psar_action_mask(TrafficState.concat(states), cavs, CFG, ROAD)  # (E, C, 5)
    for e, state in enumerate(states):
        alone = psar_action_mask(TrafficState.concat([state]), cavs[e : e + 1], CFG, ROAD)
        assert batch[e].tolist() == alone[0].tolist()
    assert batch.any(axis=-1).all()


def test_masked_logits_zero_the_masked_actions_and_keep_the_rest():
    logits = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0]])
    mask = torch.tensor([[True, False, True, False, False]])
    dist = torch.distributions.Categorical(logits=masked_logits(logits, mask))
    expected = torch.softmax(torch.tensor([1.0, 3.0]), -1)
    assert dist.probs[0, [0, 2]].tolist() == pytest.approx(expected.tolist())
    assert dist.probs[0, [1, 3, 4]].tolist() == [0.0, 0.0, 0.0]
    assert torch.isfinite(dist.entropy()).all()
    assert masked_logits(logits, torch.ones(1, 5, dtype=torch.bool)).equal(logits)


def test_psar_actions_option_is_checked():
    with pytest.raises(ConfigError, match="psar_actions"):
        EnvConfig(psar_actions="rewritten")
    cfg = TrainConfig(variant="mappo", env=dataclasses.replace(EnvConfig(), psar_actions="masked"))
    with pytest.raises(ConfigError, match="needs PSAR"):
        validate(cfg)
    with pytest.raises(ConfigError, match="critic_values"):
        validate(TrainConfig(critic_values="shared"))


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_env_observation_carries_the_mask_only_when_masked(backend):
    """Masked: PSAR executes every allowed proposal but lane changes (which it
    may still cancel for another CAV's change); unmasked: all True."""
    from diacc.envs.actions import ACTION_LANE_OFFSET
    from diacc.envs.env import BottleneckEnv

    for mode in ("proposed", "masked"):
        env = BottleneckEnv(dataclasses.replace(EnvConfig(backend=backend), psar_actions=mode))
        actor, _ = env.reset_arrays(seed=3)
        narrowed = False
        for _ in range(30):
            assert actor.action_mask.any(axis=-1).all()
            narrowed |= not actor.action_mask.all()
            # The highest allowed action: accelerate (or decelerate) whenever allowed.
            proposed = np.array([np.flatnonzero(row)[-1] for row in actor.action_mask])
            out = env.step_arrays(proposed)
            if mode == "masked":
                keeps_lane = out.alive & (ACTION_LANE_OFFSET[proposed] == 0)
                assert (out.refined_action[keeps_lane] == proposed[keeps_lane]).all()
            actor = out.actor_obs
        assert narrowed == (mode == "masked")
        env.close()
