"""The observation layout: what each row and column of the actor and critic inputs holds.

Layout (C = CAVs of the scenario, K = ``n_neighbours`` (6), T =
``history_steps`` (5, oldest first, current last), N = ``max_vehicles``,
L = ``MAX_LANES``, S = ``MAX_SEGMENTS``). All float arrays are float32 and
normalised to roughly [-1, 1]; every float feature is clipped to
[-``FEATURE_CLIP``, ``FEATURE_CLIP``] = [-5, 5] (only far-away neighbours'
dx or very crowded lane counts ever reach the clip). Padding entries are
exactly zero and masked. ``v_max`` is ``Map.max_speed_mps``; ``max_lanes``
below is ``Map.max_lanes``.

Neighbour rule (actor and critic alike): the K vehicles nearest by
``|x_j - x_i|`` among *active* vehicles whose absolute lane differs from the
ego's by at most one, the ego excluded; ties go to the lower vehicle index.

Actor (:class:`ActorObs`, one row per CAV slot):

* ``self_state`` (C, 6): x / route length, y / road width, v / v_max,
  heading (rad), lane / (max_lanes - 1), distance to the end of the ego lane
  / 100 m (clipped to [0, 1]; 1 = lane does not end within 100 m).
* ``ego_hist`` (C, T, F): the ego's own trajectory as a node (F features below).
* ``hdv_nodes``/``cav_nodes`` (C, K, T, F) and ``hdv_mask``/``cav_mask``
  (C, K) bool: the K nearest vehicles (neighbour rule above), split by type,
  each set nearest first and padded to K. Node features F = 6:
  dx / 50 m, dy / lane width, dv / v_max, heading (rad), v / v_max, is_cav,
  all relative to the ego's *current* position and speed (so a history is a
  trajectory in the ego frame). Neighbours are chosen on the current step;
  at an older step where a neighbour was not active its earliest active
  values are repeated.
* ``cav_prev_action`` (C, K) int64: the refined action each neighbouring CAV
  executed at the previous step (0 for padding).
* ``lane_stats`` (C, 3, 4) and ``lane_mask`` (C, 3): ego / left (lane + 1) /
  right (lane - 1) lane, counting the *other* active vehicles with
  ``|x_j - x_i| <= lane_window_m``: count / 10, density / (100 veh/km)
  (window length clipped to the route), mean speed / v_max, CAV share. A lane
  that does not exist in the ego's current segment (``Map.lane_exists``) is
  masked and zero.
* ``road`` (C, 4 S): static road table, one row per segment
  (start / route length, end / route length, lanes / max_lanes, present: 1,
  or the segment's speed limit / the route's highest with
  ``ObservationConfig.road_speed_limits``; 0 for absent rows).
* ``action_memory`` (C, 2) int64: the actor's proposed action and the
  PSAR-refined action of the previous step (0 at reset); passed through.
* ``action_mask`` (C, 5) bool: the actions the actor may sample (PettingZoo's
  ``action_mask``). All True here; the environment narrows it to the actions
  PSAR would execute unchanged when ``EnvConfig.psar_actions = "masked"``
  (:mod:`diacc.envs.action_mask`). Not a network input.
* ``alive`` (C,) bool: the CAV is on the road. Every other field of a row
  whose CAV is not alive is zero (masks False), except ``action_memory``.

Critic (:class:`CriticState`, one per environment):

* ``nodes`` (N, 6) and ``node_mask`` (N,): every vehicle: x / route length,
  y / road width, v / v_max, heading, lane / (max_lanes - 1), is_cav.
  Inactive vehicles and padding rows are zero and masked. Row i is vehicle i
  (a release), or with ``compact_critic`` (a demand scenario, whose V
  vehicles of the whole episode are mostly not on the road) the rows hold
  the vehicles on the road, in index order, first: N then bounds the
  vehicles on the road at once, not V.
* ``neighbours`` (N, K) int64 and ``neighbour_mask`` (N, K): indices (into
  ``nodes``) of each vehicle's K neighbours, same rule and order as the
  actor's (the actor's HDV and CAV sets together are exactly these).
* ``lane_stats`` (L, 4), ``lane_mask`` (L,): per absolute lane over the whole
  route, same four statistics (density over the length on which the lane
  exists). Lanes beyond ``Map.max_lanes`` are masked and zero.
* ``road`` (4 S,): static road table.
* ``traffic`` (4,): active vehicles / N, mean speed / v_max, CAV share of
  active vehicles, step / episode length (0 with
  ``ObservationConfig.critic_step_input = False``).

:class:`ObservationSpec` is the one description of this layout: every size,
shape, dtype and field name (what the networks read: :data:`ACTOR_KEYS`,
:data:`CRITIC_KEYS`) derives from it, without building an observation.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from diacc.config import ObservationConfig
from diacc.errors import DiaccError
from diacc.records import Batched, per_env
from diacc.sim.maps import Map

NODE_FEATURES = 6
SELF_FEATURES = 6
LANE_FEATURES = 4
CRITIC_NODE_FEATURES = 6
TRAFFIC_FEATURES = 4
ROAD_FEATURES_PER_SEGMENT = 4
MAX_SEGMENTS = 8
MAX_LANES = 6
N_ACTIONS = 5
#: Lane slots of the actor's lane statistics: ego, left, right.
LANE_SLOTS = 3
#: Every float feature is clipped to [-FEATURE_CLIP, FEATURE_CLIP].
FEATURE_CLIP = 5.0

# Normalisation scales (see the module docstring).
DX_SCALE_M = 50.0
LANE_END_SCALE_M = 100.0
COUNT_SCALE = 10.0
DENSITY_SCALE_VEH_PER_KM = 100.0


class ObservationError(DiaccError, ValueError):
    """A state or map does not fit the observation layout; one-line message."""


def clip_f32(a: np.ndarray) -> np.ndarray:
    """float32 copy clipped to the documented feature range."""
    return np.minimum(np.maximum(a, -FEATURE_CLIP), FEATURE_CLIP).astype(np.float32)


@dataclass
class ActorObs(Batched):
    """Per-CAV observations of E envs (a :class:`~diacc.records.Batched` record; an env's
    own, ``unbatched(e)``, drops E: what the PettingZoo env hands out)."""

    self_state: np.ndarray = per_env("E, C, SELF_FEATURES")  # float32
    ego_hist: np.ndarray = per_env("E, C, T, NODE_FEATURES")  # float32
    hdv_nodes: np.ndarray = per_env("E, C, K, T, NODE_FEATURES")  # float32
    hdv_mask: np.ndarray = per_env("E, C, K")  # bool
    cav_nodes: np.ndarray = per_env("E, C, K, T, NODE_FEATURES")  # float32
    cav_mask: np.ndarray = per_env("E, C, K")  # bool
    cav_prev_action: np.ndarray = per_env("E, C, K")  # int64
    lane_stats: np.ndarray = per_env("E, C, LANE_SLOTS, LANE_FEATURES")  # float32
    lane_mask: np.ndarray = per_env("E, C, LANE_SLOTS")  # bool
    road: np.ndarray = per_env("E, C, ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS")  # float32
    action_memory: np.ndarray = per_env("E, C, 2")  # int64
    # bool legal (diacc.envs.action_mask); every action for a slot without a CAV
    action_mask: np.ndarray = per_env("E, C, N_ACTIONS", pad=True)
    alive: np.ndarray = per_env("E, C")  # bool


@dataclass
class CriticState(Batched):
    """Global state of E envs (a :class:`~diacc.records.Batched` record, as
    :class:`ActorObs`)."""

    nodes: np.ndarray = per_env("E, N, CRITIC_NODE_FEATURES")  # float32
    node_mask: np.ndarray = per_env("E, N")  # bool
    neighbours: np.ndarray = per_env("E, N, K")  # int64
    neighbour_mask: np.ndarray = per_env("E, N, K")  # bool
    lane_stats: np.ndarray = per_env("E, MAX_LANES, LANE_FEATURES")  # float32
    lane_mask: np.ndarray = per_env("E, MAX_LANES")  # bool
    road: np.ndarray = per_env("E, ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS")  # float32
    traffic: np.ndarray = per_env("E, TRAFFIC_FEATURES")  # float32


#: ActorObs fields the actor networks read (``alive`` only masks the losses,
#: ``action_mask`` the action distribution).
ACTOR_KEYS = tuple(f.name for f in fields(ActorObs) if f.name not in ("alive", "action_mask"))
#: CriticState fields the critic networks read (all of them).
CRITIC_KEYS = tuple(f.name for f in fields(CriticState))


# --------------------------------------------------------------------------
# Sizes without building anything
# --------------------------------------------------------------------------
Shape = tuple[int, ...]


def check_road(road: Map) -> None:
    """One-line :class:`ObservationError` unless the layout's road and lane tables hold
    ``road`` (the trainer and the grid loader call it before anything is written)."""
    if len(road.segments) > MAX_SEGMENTS:
        raise ObservationError(
            f"map {road.name!r} has {len(road.segments)} segments; the observation "
            f"layout holds at most MAX_SEGMENTS = {MAX_SEGMENTS}"
        )
    if road.max_lanes > MAX_LANES:
        raise ObservationError(
            f"map {road.name!r} has {road.max_lanes} lanes; the observation layout "
            f"holds at most MAX_LANES = {MAX_LANES}"
        )


@dataclass(frozen=True)
class ObservationSpec:
    """Every size a network needs: the config's K, T, N and the layout's constants.

    Checkpoints store it, so a network is never fed observations of another layout.
    """

    n_neighbours: int  # K
    history_steps: int  # T
    max_vehicles: int  # N
    node_features: int = NODE_FEATURES
    self_features: int = SELF_FEATURES
    lane_slots: int = LANE_SLOTS
    lane_features: int = LANE_FEATURES
    road_features: int = ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS
    critic_node_features: int = CRITIC_NODE_FEATURES
    traffic_features: int = TRAFFIC_FEATURES
    max_lanes: int = MAX_LANES
    max_segments: int = MAX_SEGMENTS
    n_actions: int = N_ACTIONS

    def __post_init__(self) -> None:
        for name in ("n_neighbours", "history_steps", "max_vehicles"):
            if getattr(self, name) < 1:
                raise ObservationError(f"{name} must be >= 1, got {getattr(self, name)}")

    @classmethod
    def from_config(cls, cfg: ObservationConfig) -> ObservationSpec:
        """Sizes of the observation layout for a config (no map or state needed)."""
        return cls(cfg.n_neighbours, cfg.history_steps, cfg.max_vehicles)

    @classmethod
    def from_containers(cls, actor: ActorObs, critic: CriticState) -> ObservationSpec:
        """Sizes read off one actor observation and one critic state (any batch axes)."""
        history_steps, n_neighbours = actor.hdv_nodes.shape[-2], actor.hdv_nodes.shape[-3]
        return cls(n_neighbours, history_steps, critic.nodes.shape[-2])

    def actor_shapes(self, n_cavs: int) -> dict[str, tuple[Shape, np.dtype]]:
        """Field name -> (shape, dtype) of an :class:`ActorObs` with ``n_cavs`` rows."""
        c, k, t = n_cavs, self.n_neighbours, self.history_steps
        f32, i64, b = np.dtype(np.float32), np.dtype(np.int64), np.dtype(bool)
        return {
            "self_state": ((c, self.self_features), f32),
            "ego_hist": ((c, t, self.node_features), f32),
            "hdv_nodes": ((c, k, t, self.node_features), f32),
            "hdv_mask": ((c, k), b),
            "cav_nodes": ((c, k, t, self.node_features), f32),
            "cav_mask": ((c, k), b),
            "cav_prev_action": ((c, k), i64),
            "lane_stats": ((c, self.lane_slots, self.lane_features), f32),
            "lane_mask": ((c, self.lane_slots), b),
            "road": ((c, self.road_features), f32),
            "action_memory": ((c, 2), i64),
            "action_mask": ((c, self.n_actions), b),
            "alive": ((c,), b),
        }

    def critic_shapes(self) -> dict[str, tuple[Shape, np.dtype]]:
        """Field name -> (shape, dtype) of a :class:`CriticState`."""
        n, k = self.max_vehicles, self.n_neighbours
        f32, i64, b = np.dtype(np.float32), np.dtype(np.int64), np.dtype(bool)
        return {
            "nodes": ((n, self.critic_node_features), f32),
            "node_mask": ((n,), b),
            "neighbours": ((n, k), i64),
            "neighbour_mask": ((n, k), b),
            "lane_stats": ((self.max_lanes, self.lane_features), f32),
            "lane_mask": ((self.max_lanes,), b),
            "road": ((self.road_features,), f32),
            "traffic": ((self.traffic_features,), f32),
        }
