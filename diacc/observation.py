"""Shared observation builder: TrafficState -> actor observations and critic state.

The builder only reads :class:`~diacc.state.TrafficState` arrays and the
:class:`~diacc.maps.Map`; it never knows which backend produced the state.

Layout (C = CAVs of the scenario, K = ``n_neighbours`` (6), T =
``history_steps`` (5, oldest first, current last), N = ``max_vehicles``,
L = ``MAX_LANES``, S = ``MAX_SEGMENTS``). All float arrays are float32 and
normalised to roughly [-1, 1]; padding entries are exactly zero and masked.

Actor (:class:`ActorObs`, one row per CAV slot):

* ``self_state`` (C, 6): x / route length, y / road width, v / v_max,
  heading (rad), lane / (max_lanes - 1), distance to the end of the ego lane
  / 100 m (clipped to 1; 1 = lane does not end ahead).
* ``ego_hist`` (C, T, F): the ego's own trajectory as a node (F features below).
* ``hdv_nodes``/``cav_nodes`` (C, K, T, F) and ``hdv_mask``/``cav_mask``
  (C, K) bool: the K nearest vehicles (by |dx|) in the ego lane and the two
  adjacent lanes, split by type, nearest first. Node features F = 6:
  dx / 50 m, dy / lane width, dv / v_max, heading (rad), v / v_max, is_cav,
  all relative to the ego's *current* position and speed (so a history is a
  trajectory in the ego frame).
* ``cav_prev_action`` (C, K) int64: the refined action each neighbouring CAV
  executed at the previous step (0 for padding).
* ``lane_stats`` (C, 3, 4) and ``lane_mask`` (C, 3): ego / left / right lane
  within +-``lane_window_m``: count / 10, density / (100 veh/km), mean speed
  / v_max, CAV share. A lane that does not exist at the ego's position is
  masked and zero.
* ``road`` (C, 4 S): static road table, one row per segment
  (start / route length, end / route length, lanes / max lanes, present).
* ``action_memory`` (C, 2) int64: the actor's proposed action and the
  PSAR-refined action of the previous step (0 at reset).
* ``alive`` (C,) bool: the CAV is on the road.

Critic (:class:`CriticState`, one per environment):

* ``nodes`` (N, 6) and ``node_mask`` (N,): every vehicle: x / route length,
  y / road width, v / v_max, heading, lane / (max_lanes - 1), is_cav.
* ``neighbours`` (N, K) int64 and ``neighbour_mask`` (N, K): indices (into
  ``nodes``) of each vehicle's K neighbours, same rule as the actor's.
* ``lane_stats`` (L, 4), ``lane_mask`` (L,): per absolute lane over the whole
  route, same four statistics.
* ``road`` (4 S,): static road table.
* ``traffic`` (4,): active vehicles / N, mean speed / v_max, CAV share of
  active vehicles, step / episode length.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

NODE_FEATURES = 6
SELF_FEATURES = 6
LANE_FEATURES = 4
CRITIC_NODE_FEATURES = 6
TRAFFIC_FEATURES = 4
ROAD_FEATURES_PER_SEGMENT = 4
MAX_SEGMENTS = 8
MAX_LANES = 6
N_ACTIONS = 5


@dataclass
class ActorObs:
    """Per-CAV observations; leading axis C (or any batch axes before it)."""

    self_state: np.ndarray  # (C, SELF_FEATURES) float32
    ego_hist: np.ndarray  # (C, T, NODE_FEATURES) float32
    hdv_nodes: np.ndarray  # (C, K, T, NODE_FEATURES) float32
    hdv_mask: np.ndarray  # (C, K) bool
    cav_nodes: np.ndarray  # (C, K, T, NODE_FEATURES) float32
    cav_mask: np.ndarray  # (C, K) bool
    cav_prev_action: np.ndarray  # (C, K) int64
    lane_stats: np.ndarray  # (C, 3, LANE_FEATURES) float32
    lane_mask: np.ndarray  # (C, 3) bool
    road: np.ndarray  # (C, ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS) float32
    action_memory: np.ndarray  # (C, 2) int64
    alive: np.ndarray  # (C,) bool


@dataclass
class CriticState:
    """Global state of one environment (or a batch of them on leading axes)."""

    nodes: np.ndarray  # (N, CRITIC_NODE_FEATURES) float32
    node_mask: np.ndarray  # (N,) bool
    neighbours: np.ndarray  # (N, K) int64
    neighbour_mask: np.ndarray  # (N, K) bool
    lane_stats: np.ndarray  # (MAX_LANES, LANE_FEATURES) float32
    lane_mask: np.ndarray  # (MAX_LANES,) bool
    road: np.ndarray  # (ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS,) float32
    traffic: np.ndarray  # (TRAFFIC_FEATURES,) float32


def stack(items: list) -> ActorObs | CriticState:
    """Stack containers of the same type along a new leading axis."""
    cls = type(items[0])
    return cls(**{f.name: np.stack([getattr(i, f.name) for i in items]) for f in fields(cls)})
