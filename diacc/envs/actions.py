"""The CAV action set (the paper's five discrete actions) and what each action asks of a backend.

One small module because the environment, PSAR, the baselines and the
renderer all speak in these codes; the environment turns them into
:class:`~diacc.sim.backends.base.CavCommands`.
"""

from __future__ import annotations

import numpy as np

from diacc.config import SimConfig
from diacc.sim.kinematics import lane_change_reach_m
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, take

REMAIN, LANE_LEFT, LANE_RIGHT, ACCELERATE, DECELERATE = 0, 1, 2, 3, 4
ACTION_NAMES = ("remain", "left", "right", "accelerate", "decelerate")
#: Lane offset of each action (+1 = one lane to the left), indexed by action.
ACTION_LANE_OFFSET = np.array([0, +1, -1, 0, 0], dtype=np.int64)


def action_speed_change_mps(action: np.ndarray, sim: SimConfig) -> np.ndarray:
    """(C,) speed change of each action: ``+speed_change_mps`` for accelerate,
    ``-speed_change_mps * decelerate_scale`` for decelerate, else 0.

    The paper's actions move the target speed by +-2 m/s per 1 s step, so the policy
    can brake at 2 m/s^2 where a human ahead may brake at 4-7; PSAR brakes harder
    when it must. ``decelerate_scale`` lets a policy without PSAR do so too.
    """
    action = np.asarray(action)
    up_mps, down_mps = sim.speed_change_mps, sim.speed_change_mps * sim.decelerate_scale
    return np.where(action == ACCELERATE, up_mps, np.where(action == DECELERATE, -down_mps, 0.0))


def lane_change_allowed(
    state: TrafficState, cav_index: np.ndarray, action: np.ndarray, road: Map, sim: SimConfig
) -> np.ndarray:
    """(..., C) bool: the action is a lane change the road allows (``Map.lane_change_allowed``)."""
    return road.lane_change_allowed(
        take(state.segment, cav_index),
        take(state.lane, cav_index),
        ACTION_LANE_OFFSET[action],
        take(state.x_m, cav_index),
        lane_change_reach_m(
            take(state.speed_mps, cav_index), sim.step_s, take(state.length_m, cav_index)
        ),
    )
