"""The agents' lateral frame: every road seen with its lanes ending on the left.

Why: every shipped map drops its *left* lanes, so an agent trained on them
learns "move right before the drop". On a road that drops its *right* lanes
that agent steers its CAVs into the ending lanes and traffic collapses
(measured, train-50 mirrored, highway: +698 % delay against the same-mix
baseline; ``benchmarks/studies/learning-evidence/results/zero-shot``). The bottleneck
is mirror-symmetric apart from the human drivers' own habits, so under
``ObservationConfig.lateral_frame = "drop-left"`` (the default) a road that
drops its right lanes is reflected before the agents see it: the map they
observe drops on the left, the traffic state is mirrored across the road
(lane ``l`` -> ``max_lanes - 1 - l``, ``y`` -> road width - ``y``, heading
-> -heading) and "left"/"right" swap in every action that crosses the
boundary. On a road that drops on the left this is the identity, so agents
trained on the shipped maps behave exactly as before there.

Where the reflection happens (and nowhere else):

* :class:`~diacc.envs.observation.ObservationBuilder` observes the mirrored state on
  the mirrored map (actor and critic alike);
* :func:`~diacc.envs.env.decide` turns the agents' actions into the world's before
  PSAR and the backend, and PSAR's executed actions back, so every action the
  environment speaks (proposed, refined, action memory, the PettingZoo
  ``refined_action``) is in the agents' frame;
* :func:`~diacc.envs.action_mask.with_action_mask` swaps the mask's left/right columns.

The backend, PSAR, reward, metrics and renderer all keep the world frame.
``lateral_frame = "world"`` is the literal reading: observations and actions in
the road's own lane numbering.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from diacc.config import LATERAL_FRAMES
from diacc.envs.actions import ACCELERATE, DECELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState

__all__ = ["LATERAL_FRAMES", "agent_map", "is_mirrored", "mirror_actions", "mirror_state"]

#: The action each action becomes in the mirrored frame (its own inverse).
MIRRORED_ACTION = np.array([REMAIN, LANE_RIGHT, LANE_LEFT, ACCELERATE, DECELERATE], np.int64)


def is_mirrored(road: Map, lateral_frame: str) -> bool:
    """Whether the agents see ``road`` reflected: it drops its right lanes under ``drop-left``."""
    return lateral_frame == "drop-left" and road.drop_side == "right"


def agent_map(road: Map, lateral_frame: str) -> Map:
    """The map as the agents see it: ``road`` itself, or its mirror image."""
    return dataclasses.replace(road, drop_side="left") if is_mirrored(road, lateral_frame) else road


def mirror_state(state: TrafficState, road: Map) -> TrafficState:
    """A copy of ``state`` reflected across ``road`` (any leading env axes).

    Lane ``l`` of ``L = road.max_lanes`` becomes ``L - 1 - l``, the centre's
    ``y`` becomes ``L * lane_width - y`` (so lane centres map onto lane
    centres), headings change sign. Everything longitudinal is unchanged.
    """
    out = state.copy()
    out.lane = (road.max_lanes - 1 - state.lane).astype(state.lane.dtype)
    out.y_m = road.max_lanes * road.lane_width_m - state.y_m
    out.heading_rad = -state.heading_rad
    return out


def mirror_actions(actions: np.ndarray) -> np.ndarray:
    """Actions with left and right swapped (world <-> mirrored frame; any shape)."""
    return MIRRORED_ACTION[np.asarray(actions, dtype=np.int64)]
