"""Shared observation builder: TrafficState -> actor observations and critic state.

The builder only reads :class:`~diacc.sim.state.TrafficState` arrays and the
:class:`~diacc.sim.maps.Map`; it never knows which backend produced the state.

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

import math
from dataclasses import dataclass, fields

import numpy as np

from diacc.config import ObservationConfig
from diacc.envs.lateral_frame import agent_map, is_mirrored, mirror_state
from diacc.errors import DiaccError
from diacc.sim.maps import Map
from diacc.sim.state import (
    TrafficState,
    flat_offsets,
    on_road_window,
    stack_last,
    take,
    take_last,
    take_rows,
)

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
    lane_stats: np.ndarray  # (C, LANE_SLOTS, LANE_FEATURES) float32
    lane_mask: np.ndarray  # (C, 3) bool
    road: np.ndarray  # (C, ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS) float32
    action_memory: np.ndarray  # (C, 2) int64
    action_mask: np.ndarray  # (C, N_ACTIONS) bool legal actions (diacc.envs.action_mask); all True
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


#: ActorObs fields the actor networks read (``alive`` only masks the losses,
#: ``action_mask`` the action distribution).
ACTOR_KEYS = tuple(f.name for f in fields(ActorObs) if f.name not in ("alive", "action_mask"))
#: CriticState fields the critic networks read (all of them).
CRITIC_KEYS = tuple(f.name for f in fields(CriticState))


def stack(items: list) -> ActorObs | CriticState:
    """Stack containers of the same type along a new leading axis."""
    cls = type(items[0])
    return cls(**{f.name: np.stack([getattr(i, f.name) for i in items]) for f in fields(cls)})


def unstack(batch: ActorObs | CriticState, e: int, copy: bool = False) -> ActorObs | CriticState:
    """Entry ``e`` of a container whose fields have a leading (env) axis (views, or copies)."""
    return type(batch)(
        **{
            f.name: getattr(batch, f.name)[e].copy() if copy else getattr(batch, f.name)[e]
            for f in fields(batch)
        }
    )


def concat(items: list):
    """Containers of the same type joined along their leading (env) axis."""
    if len(items) == 1:
        return items[0]
    cls = type(items[0])
    return cls(**{f.name: np.concatenate([getattr(i, f.name) for i in items]) for f in fields(cls)})


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


# --------------------------------------------------------------------------
# Builder
# --------------------------------------------------------------------------
@dataclass
class _History:
    """The last T states' per-vehicle fields, oldest first: arrays (..., T, V)."""

    x_m: np.ndarray
    y_m: np.ndarray
    speed_mps: np.ndarray
    heading_rad: np.ndarray
    active: np.ndarray

    @classmethod
    def filled(cls, state: TrafficState, steps: int) -> _History:
        """T copies of ``state`` (any leading env axes)."""
        return cls(
            *(np.repeat(getattr(state, f.name)[..., None, :], steps, axis=-2) for f in fields(cls))
        )

    def fill_rows(self, rows: np.ndarray, state: TrafficState) -> None:
        """Envs ``rows`` of a batch history start afresh: T copies of their ``state`` rows."""
        for f in fields(self):
            getattr(self, f.name)[rows] = getattr(state, f.name)[rows, None, :]

    def push(self, state: TrafficState) -> None:
        for f in fields(self):
            arr = getattr(self, f.name)  # (..., T, V)
            arr[..., :-1, :] = arr[..., 1:, :]
            arr[..., -1, :] = getattr(state, f.name)


@dataclass
class _Frame:
    """What the observations of one instant are built from: the state, its history
    and its neighbour sets; every array with the state's leading (env) axes.

    The neighbour sets are searched when first needed (None until then), so
    that :meth:`ObservationBuilder.observe_batch` searches a batch's in one call.
    """

    state: TrafficState
    hist: _History  # fields (..., T, V)
    nbr: np.ndarray | None = None  # (..., V, K) int64
    nbr_mask: np.ndarray | None = None  # (..., V, K) bool


class ObservationBuilder:
    """Turns the stream of TrafficStates of one episode into actor/critic inputs.

    Call :meth:`reset` with the first state of an episode, :meth:`push` with
    every following state, then :meth:`actor` and :meth:`critic` for the
    current (last pushed) state. Per-step work is vectorised over vehicles:
    one (V, V) distance table per step serves both the actor's and the
    critic's neighbour sets, which keeps the two consistent by construction.

    The stream may be one env's states (V,) or a batch's (E, V): then every
    array gains the leading env axis, :meth:`reset_rows` restarts single envs
    and the results are those of E builders (the step of
    :class:`diacc.envs.batch.EnvBatch`).
    """

    def __init__(
        self, road: Map, cfg: ObservationConfig, episode_steps: int, compact_critic: bool = False
    ) -> None:
        """``compact_critic``: the critic's rows hold the vehicles on the road first
        (module docstring; the env sets it for demand scenarios)."""
        check_road(road)
        if episode_steps < 1:
            raise ObservationError(f"episode_steps must be >= 1, got {episode_steps}")
        # The agents' frame (diacc.envs.lateral_frame): every state is observed reflected when
        # the road drops its right lanes; ``road`` is then the mirrored map.
        self.mirrored = is_mirrored(road, cfg.lateral_frame)
        road = agent_map(road, cfg.lateral_frame)
        self.road = road
        self.cfg = cfg
        self.episode_steps = int(episode_steps)
        self.compact_critic = compact_critic
        self._spec = ObservationSpec.from_config(cfg)

        # Static map quantities, computed once.
        self._route_m = road.length_m
        self._v_max_mps = road.max_speed_mps
        self._lane_w_m = road.lane_width_m
        self._road_w_m = road.max_lanes * road.lane_width_m
        self._lane_norm = float(max(road.max_lanes - 1, 1))
        exists = road.lane_exists()  # (S, Lm)
        # One False column on each side so that lane -1 and lane max_lanes index safely.
        self._exists_pad = np.pad(exists, ((0, 0), (1, 1)), constant_values=False)  # (S, Lm+2)
        self._lane_end_m = road.lane_end_m()  # (S, Lm)
        seg_len_m = np.array([s.length_m for s in road.segments])  # (S,)
        lane_len_km = (exists * seg_len_m[:, None]).sum(axis=0) / 1000.0  # (Lm,)
        self._lane_len_km = np.zeros(MAX_LANES)
        self._lane_len_km[: road.max_lanes] = lane_len_km
        table = np.zeros((MAX_SEGMENTS, ROAD_FEATURES_PER_SEGMENT), np.float32)  # (S_max, 4)
        n_seg = len(road.segments)
        table[:n_seg, 0] = road.segment_starts_m / self._route_m
        table[:n_seg, 1] = road.segment_ends_m / self._route_m
        table[:n_seg, 2] = [s.lanes / road.max_lanes for s in road.segments]
        table[:n_seg, 3] = (
            [seg.speed_limit_mps / self._v_max_mps for seg in road.segments]
            if cfg.road_speed_limits
            else 1.0
        )
        self._road_table = table.reshape(-1)  # (4 S_max,)

        self._frame: _Frame | None = None

    # ---- sizes -----------------------------------------------------------
    def spec(self) -> ObservationSpec:
        """Sizes of this builder's observations (:class:`ObservationSpec`)."""
        return self._spec

    # ---- state stream ------------------------------------------------------
    def reset(self, state: TrafficState) -> None:
        """Start an episode: the whole history holds copies of ``state``."""
        self._check_state(state, expect_vehicles=None)
        state = self._in_frame(state)
        self._frame = _Frame(state, _History.filled(state, self.cfg.history_steps))

    def reset_rows(self, rows: np.ndarray, state: TrafficState) -> None:
        """Envs ``rows`` of a batch start new episodes: ``state`` is the whole (E, V) batch
        with those rows' first states; their histories are refilled, the others kept."""
        if self._frame is None:
            raise ObservationError("reset_rows() called before reset(); start the batch first")
        self._check_state(state, expect_vehicles=self._frame.state.n_vehicles)
        state = self._in_frame(state)
        self._frame.hist.fill_rows(rows, state)
        self._frame = _Frame(state, self._frame.hist)

    def push(self, state: TrafficState) -> None:
        """Append the state of a new step (one env's, or a batch's, :meth:`reset` with one);
        the oldest history entry drops out."""
        if self._frame is None:
            raise ObservationError("push() called before reset(); start the episode first")
        self._check_state(state, expect_vehicles=self._frame.state.n_vehicles)
        state = self._in_frame(state)
        self._frame.hist.push(state)
        self._frame = _Frame(state, self._frame.hist)

    @property
    def neighbours(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, K) int64 neighbour indices and (V, K) bool mask of the current state."""
        frame = self._require_frame()
        return frame.nbr, frame.nbr_mask

    # ---- actor -------------------------------------------------------------
    def actor(
        self,
        cav_index: np.ndarray,
        action_memory: np.ndarray,
        last_refined_action: np.ndarray,
    ) -> ActorObs:
        """Observations of the CAV slots ``cav_index`` for the current state.

        Args:
            cav_index: (C,) vehicle indices of the CAV slots, fixed for the episode.
            action_memory: (C, 2) int64 proposed and PSAR-refined action of the
                previous step per slot; copied into the observation.
            last_refined_action: (V,) int64 refined action each vehicle executed at
                the previous step (only CAV entries are read).
        """
        return self._actor(self._require_frame(), cav_index, action_memory, last_refined_action)

    def observe_rows(
        self,
        rows: np.ndarray,
        cav_index: np.ndarray,
        action_memory: np.ndarray,
        last_refined_action: np.ndarray,
    ) -> tuple[ActorObs, CriticState]:
        """:meth:`actor` and :meth:`critic` of envs ``rows`` of a batch alone (e.g. those
        that just started new episodes); the arguments hold those rows only."""
        frame = self._current()
        hist = _History(*(getattr(frame.hist, f.name)[rows] for f in fields(_History)))
        part = frame.state.envs(rows)
        sub = _Frame(part, hist)
        sub.nbr, sub.nbr_mask = self._neighbours(part)
        return self._actor(sub, cav_index, action_memory, last_refined_action), self._critic(sub)

    # ---- critic ------------------------------------------------------------
    def critic(self) -> CriticState:
        """Global state of the current step, padded to ``max_vehicles``."""
        return self._critic(self._require_frame())

    # ---- internals -----------------------------------------------------------
    def _in_frame(self, state: TrafficState) -> TrafficState:
        """A copy of ``state`` in the agents' frame (mirrored or as it is)."""
        return mirror_state(state, self.road) if self.mirrored else state.copy()

    def _actor(
        self,
        frame: _Frame,
        cav_index: np.ndarray,
        action_memory: np.ndarray,
        last_refined_action: np.ndarray,
    ) -> ActorObs:
        """:meth:`actor` of a frame with any leading (env) axes ``...``."""
        state, hist = frame.state, frame.hist
        lead = state.x_m.shape[:-1]
        n_veh, k = state.n_vehicles, self.cfg.n_neighbours
        cav_index = np.asarray(cav_index)
        if (
            cav_index.ndim != len(lead) + 1
            or cav_index.shape[:-1] != lead
            or not np.issubdtype(cav_index.dtype, np.integer)
        ):
            raise ObservationError(f"cav_index must be a 1-D integer array, got {cav_index!r}")
        if cav_index.size and (cav_index.min() < 0 or cav_index.max() >= n_veh):
            raise ObservationError(f"cav_index {cav_index.tolist()} out of range [0, {n_veh})")
        action_memory = np.asarray(action_memory)
        if action_memory.shape != cav_index.shape + (2,):
            raise ObservationError(
                f"action_memory must have shape {cav_index.shape + (2,)}, got {action_memory.shape}"
            )
        last_refined_action = np.asarray(last_refined_action)
        if last_refined_action.shape != state.x_m.shape:
            raise ObservationError(
                f"last_refined_action must have shape {state.x_m.shape}, "
                f"got {last_refined_action.shape}"
            )

        alive = take(state.active, cav_index)  # (..., C)
        ego_x = take(state.x_m, cav_index)  # (..., C)
        ego_y = take(state.y_m, cav_index)
        ego_v = take(state.speed_mps, cav_index)
        ego_lane = take(state.lane, cav_index).astype(np.int64)
        ego_seg = take(state.segment, cav_index).astype(np.int64)

        # Self features.
        lane_clip = np.minimum(np.maximum(ego_lane, 0), self.road.max_lanes - 1)
        seg_clip = np.minimum(np.maximum(ego_seg, 0), len(self.road.segments) - 1)
        to_end_m = self._lane_end_m[seg_clip, lane_clip] - ego_x  # (..., C)
        self_state = stack_last(
            [
                ego_x / self._route_m,
                ego_y / self._road_w_m,
                ego_v / self._v_max_mps,
                take(state.heading_rad, cav_index),
                ego_lane / self._lane_norm,
                np.minimum(np.maximum(to_end_m / LANE_END_SCALE_M, 0.0), 1.0),
            ],
        )  # (..., C, 6)

        # Neighbour sets: the current K nearest, split by type, each compacted nearest first.
        rows = cav_index[..., None]  # (..., C, 1)
        sel = take_rows(frame.nbr, cav_index)  # (..., C, K)
        sel_mask = take_rows(frame.nbr_mask, cav_index)  # (..., C, K)
        sel_cav = sel_mask & take(state.is_cav, sel)  # (..., C, K)
        hdv_idx, hdv_mask = _compact(sel, sel_mask & ~sel_cav)  # (..., C, K) each
        cav_idx, cav_mask = _compact(sel, sel_cav)

        # Node histories in the ego's current frame, all sets in one gather.
        idx = np.concatenate([rows, hdv_idx, cav_idx], axis=-1)  # (..., C, 1+2K)
        valid = np.concatenate([alive[..., None], hdv_mask, cav_mask], axis=-1)
        nodes = self._relative_nodes(hist, state, idx, ego_x, ego_y, ego_v)  # (..., C, M, T, F)
        nodes *= valid[..., None, None]
        ego_hist = nodes[..., 0, :, :]  # (..., C, T, F)
        hdv_nodes = nodes[..., 1 : 1 + k, :, :]  # (..., C, K, T, F)
        cav_nodes = nodes[..., 1 + k :, :, :]

        cav_prev_action = np.where(cav_mask, take(last_refined_action, cav_idx), 0)
        cav_prev_action = cav_prev_action.astype(np.int64)

        lane_stats, lane_mask = self._ego_lane_stats(state, cav_index, ego_lane, ego_seg)
        lane_mask &= alive[..., None]
        lane_stats *= lane_mask[..., None]

        road = np.broadcast_to(self._road_table, cav_index.shape + self._road_table.shape)
        road = road * alive[..., None]  # (..., C, 4S)
        self_state = self_state * alive[..., None]

        return ActorObs(
            self_state=_f32(self_state),
            ego_hist=_f32(ego_hist),
            hdv_nodes=_f32(hdv_nodes),
            hdv_mask=hdv_mask & alive[..., None],
            cav_nodes=_f32(cav_nodes),
            cav_mask=cav_mask & alive[..., None],
            cav_prev_action=cav_prev_action * alive[..., None],
            lane_stats=_f32(lane_stats),
            lane_mask=lane_mask,
            road=_f32(road),
            action_memory=action_memory.astype(np.int64, copy=True),
            action_mask=np.ones(cav_index.shape + (N_ACTIONS,), bool),
            alive=alive.copy(),
        )

    def _critic(self, frame: _Frame) -> CriticState:
        """:meth:`critic` of a frame with any leading (env) axes ``...``."""
        state = frame.state
        lead = state.x_m.shape[:-1]
        n_veh, n_max, k = state.n_vehicles, self.cfg.max_vehicles, self.cfg.n_neighbours
        active = state.active  # (..., V)

        nodes = np.zeros(lead + (n_max, CRITIC_NODE_FEATURES), np.float64)  # (..., N, 6)
        node_mask = np.zeros(lead + (n_max,), bool)
        neighbours = np.zeros(lead + (n_max, k), np.int64)  # (..., N, K)
        neighbour_mask = np.zeros(lead + (n_max, k), bool)
        if self.compact_critic:
            vehicle, row_of = _on_road_rows(active, n_max)  # (..., R), (..., V)

            def of_rows(values: np.ndarray) -> np.ndarray:  # (..., V) -> (..., R)
                return take(values, vehicle)

            n_rows = vehicle.shape[-1]
            node_mask[..., :n_rows] = take(active, vehicle)
            nbr_mask = take_rows(frame.nbr_mask, vehicle) & node_mask[..., :n_rows, None]
            nbr = take(row_of, take_rows(frame.nbr, vehicle))  # (..., R, K) neighbours' rows
            neighbours[..., :n_rows, :] = np.where(nbr_mask, nbr, 0)
            neighbour_mask[..., :n_rows, :] = nbr_mask
        else:
            n_rows = n_veh

            def of_rows(values: np.ndarray) -> np.ndarray:  # every vehicle a row, in order
                return values

            node_mask[..., :n_veh] = active
            neighbours[..., :n_veh, :] = frame.nbr
            neighbour_mask[..., :n_veh, :] = frame.nbr_mask
        nodes[..., :n_rows, :] = (
            stack_last(
                [
                    of_rows(state.x_m) / self._route_m,
                    of_rows(state.y_m) / self._road_w_m,
                    of_rows(state.speed_mps) / self._v_max_mps,
                    of_rows(state.heading_rad),
                    of_rows(state.lane) / self._lane_norm,
                    of_rows(state.is_cav).astype(np.float64),
                ],
            )
            * node_mask[..., :n_rows, None]
        )

        # Per absolute lane over the whole route: sums over vehicles, in vehicle order.
        lane = np.where(active, state.lane, MAX_LANES).astype(np.int64)  # inactive: spare bin
        in_lane = lane[..., None] == np.arange(MAX_LANES)  # (..., V, L)

        def per_lane(weights: np.ndarray) -> np.ndarray:  # (..., V) -> (..., L)
            return np.where(in_lane, weights[..., None], 0.0).sum(axis=-2)

        count = per_lane(np.ones(state.x_m.shape))
        n_cav = per_lane(state.is_cav.astype(np.float64))
        speed_sum = per_lane(state.speed_mps)
        lane_mask = np.broadcast_to(np.arange(MAX_LANES) < self.road.max_lanes, lead + (MAX_LANES,))
        safe = np.maximum(count, 1.0)
        lane_stats = (
            stack_last(
                [
                    count / COUNT_SCALE,
                    count / np.maximum(self._lane_len_km, 1e-9) / DENSITY_SCALE_VEH_PER_KM,
                    speed_sum / safe / self._v_max_mps,
                    n_cav / safe,
                ],
            )
            * lane_mask[..., None]
        )  # (..., L, 4)

        n_active = active.sum(axis=-1)  # (...,)
        step_fraction = np.asarray(state.step) / self.episode_steps  # (...,)
        if not self.cfg.critic_step_input:  # matched horizons: no clock for the critic
            step_fraction = np.zeros_like(step_fraction)
        safe_active = np.maximum(n_active, 1)
        traffic = stack_last(
            [
                n_active / n_max,
                np.where(active, state.speed_mps, 0.0).sum(axis=-1) / safe_active / self._v_max_mps,
                (state.is_cav & active).sum(axis=-1) / safe_active,
                step_fraction,
            ],
        )
        return CriticState(
            nodes=_f32(nodes),
            node_mask=node_mask,
            neighbours=neighbours,
            neighbour_mask=neighbour_mask,
            lane_stats=_f32(lane_stats),
            lane_mask=lane_mask.copy(),
            road=np.broadcast_to(self._road_table, lead + self._road_table.shape).copy(),
            traffic=_f32(traffic),
        )

    def _current(self) -> _Frame:
        if self._frame is None:
            raise ObservationError("no state yet; call reset() with the first state")
        return self._frame

    def _require_frame(self) -> _Frame:
        """The current frame with its neighbour sets."""
        frame = self._current()
        if frame.nbr is None:
            frame.nbr, frame.nbr_mask = self._neighbours(frame.state)
        return frame

    def _check_state(self, state: TrafficState, expect_vehicles: int | None) -> None:
        n_veh = state.n_vehicles
        if self.compact_critic:
            on_road = int(state.active.sum(axis=-1).max(initial=0))
            if on_road > self.cfg.max_vehicles:
                raise ObservationError(
                    f"{on_road} vehicles are on the road but ObservationConfig.max_vehicles is "
                    f"{self.cfg.max_vehicles}; raise obs.max_vehicles"
                )
        elif n_veh > self.cfg.max_vehicles:
            raise ObservationError(
                f"state has {n_veh} vehicles but ObservationConfig.max_vehicles is "
                f"{self.cfg.max_vehicles}; raise obs.max_vehicles"
            )
        if expect_vehicles is not None and n_veh != expect_vehicles:
            raise ObservationError(
                f"state has {n_veh} vehicles but the episode started with {expect_vehicles}"
            )
        act = state.active
        bad_lane = act & ((state.lane < 0) | (state.lane >= self.road.max_lanes))
        bad_seg = act & ((state.segment < 0) | (state.segment >= len(self.road.segments)))
        if bad_lane.any() or bad_seg.any():
            at = tuple(np.argwhere(bad_lane | bad_seg)[0])  # (i,) or, in a batch, (e, i)
            raise ObservationError(
                f"vehicle {at[-1]} has lane {int(state.lane[at])} / segment "
                f"{int(state.segment[at])}, "
                f"outside map {self.road.name!r} ({self.road.max_lanes} lanes, "
                f"{len(self.road.segments)} segments)"
            )

    def _neighbours(self, state: TrafficState) -> tuple[np.ndarray, np.ndarray]:
        """K nearest active vehicles in same/adjacent lanes for every vehicle, (..., V, K) each.

        Searched within :func:`~diacc.sim.state.on_road_window` alone (vehicles off
        the road have no neighbours and are none): the (W, W) distance table
        scales with the vehicles on the road, not with a demand episode's V.
        """
        k = self.cfg.n_neighbours
        lo, hi = on_road_window(state.active)
        part = state if hi - lo == state.n_vehicles else state.vehicles(lo, hi)
        n_win = hi - lo
        x, lane, act = part.x_m, part.lane.astype(np.int64), part.active
        i_, j_ = (Ellipsis, slice(None), None), (Ellipsis, None, slice(None))  # [..., i, j]
        dist = np.abs(x[j_] - x[i_])  # (..., W, W) ego i, other j
        ok = (np.abs(lane[j_] - lane[i_]) <= 1) & act[j_] & act[i_] & ~np.eye(n_win, dtype=bool)
        dist = np.where(ok, dist, np.inf)
        if n_win < k:  # fewer candidates than slots: pad with never-chosen columns
            pad = [(0, 0)] * (dist.ndim - 1) + [(0, k - n_win)]
            dist = np.pad(dist, pad, constant_values=np.inf)
        order = np.argsort(dist, axis=-1, kind="stable")[..., :k]  # (..., W, K)
        nbr = np.zeros(state.x_m.shape + (k,), np.int64)  # (..., V, K)
        mask = np.zeros(state.x_m.shape + (k,), bool)
        mask[..., lo:hi, :] = np.isfinite(take_last(dist, order))
        nbr[..., lo:hi, :] = np.where(mask[..., lo:hi, :], lo + order, 0)
        return nbr, mask

    def _relative_nodes(
        self,
        hist: _History,
        state: TrafficState,
        idx: np.ndarray,
        ego_x: np.ndarray,
        ego_y: np.ndarray,
        ego_v: np.ndarray,
    ) -> np.ndarray:
        """Node features (..., C, M, T, F) of vehicles ``idx`` (..., C, M) in each ego's frame."""
        steps, n_veh = self.cfg.history_steps, state.n_vehicles
        # Vehicles only leave, so an inactive past entry means "not yet on the
        # road": use the earliest step at which the vehicle was active instead.
        first = np.argmax(hist.active, axis=-2)  # (..., V) 0 if never active
        t_of = np.maximum(np.arange(steps), take(first, idx)[..., None])  # (..., C, M, T)
        lead = state.x_m.shape[:-1]
        # Into the flattened (..., T, V) history of every env: one index for the four
        # gathers (a flat take costs a fraction of fancy indexing by env and vehicle).
        flat = t_of * n_veh + idx[..., None] + flat_offsets(lead, steps * n_veh, 3)

        def gather(a: np.ndarray) -> np.ndarray:  # (..., T, V) -> (..., C, M, T)
            return np.ascontiguousarray(a).reshape(-1).take(flat)

        x, y = gather(hist.x_m), gather(hist.y_m)
        v, heading = gather(hist.speed_mps), gather(hist.heading_rad)
        is_cav = np.broadcast_to(take(state.is_cav, idx)[..., None], x.shape)
        feats = stack_last(
            [
                (x - ego_x[..., None, None]) / DX_SCALE_M,
                (y - ego_y[..., None, None]) / self._lane_w_m,
                (v - ego_v[..., None, None]) / self._v_max_mps,
                heading,
                v / self._v_max_mps,
                is_cav.astype(np.float64),
            ],
        )  # (..., C, M, T, F)
        return feats

    def _ego_lane_stats(
        self,
        state: TrafficState,
        cav_index: np.ndarray,
        ego_lane: np.ndarray,
        ego_seg: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Ego / left / right lane statistics (..., C, 3, 4) and existence mask (..., C, 3)."""
        w_m = self.cfg.lane_window_m
        target = ego_lane[..., None] + np.array([0, 1, -1])  # (..., C, 3) absolute lanes
        seg = np.minimum(np.maximum(ego_seg, 0), len(self.road.segments) - 1)
        exists = self._exists_pad[
            seg[..., None], np.minimum(np.maximum(target + 1, 0), self.road.max_lanes + 1)
        ]
        ego_x = take(state.x_m, cav_index)  # (..., C)
        in_win = (np.abs(state.x_m[..., None, :] - ego_x[..., None]) <= w_m) & state.active[
            ..., None, :
        ]  # (..., C, V)
        in_win &= np.arange(state.n_vehicles) != cav_index[..., None]  # ego excluded
        hit = in_win[..., None, :] & (
            state.lane[..., None, None, :] == target[..., None]
        )  # (..., C, 3, V)
        count = hit.sum(axis=-1).astype(np.float64)  # (..., C, 3)
        n_cav = (hit & state.is_cav[..., None, None, :]).sum(axis=-1)
        speed_sum = (hit * state.speed_mps[..., None, None, :]).sum(axis=-1)
        win_km = (np.minimum(ego_x + w_m, self._route_m) - np.maximum(ego_x - w_m, 0.0)) / 1000.0
        safe = np.maximum(count, 1.0)
        stats = stack_last(
            [
                count / COUNT_SCALE,
                count / np.maximum(win_km, 1e-9)[..., None] / DENSITY_SCALE_VEH_PER_KM,
                speed_sum / safe / self._v_max_mps,
                n_cav / safe,
            ],
        )  # (..., C, 3, 4)
        return stats, exists


def _on_road_rows(active: np.ndarray, n_max: int) -> tuple[np.ndarray, np.ndarray]:
    """The compact critic's rows: vehicles on the road first, in index order.

    Args:
        active: (..., V) bool, at most ``n_max`` True per env (checked on push).

    Returns:
        (..., R) int64 vehicle of each row, R = min(V, n_max) (rows past the
        vehicles on the road hold vehicles off it), and (..., V) int64 row of
        each vehicle on the road (0 for the others).
    """
    n_rows = min(active.shape[-1], n_max)
    vehicle = np.argsort(~active, axis=-1, kind="stable")[..., :n_rows]  # (..., R)
    row_of = np.where(active, np.cumsum(active, axis=-1) - 1, 0)  # (..., V)
    return vehicle.astype(np.int64), row_of


def _compact(idx: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move kept entries of each row to the front, order preserved; pad with 0 / False.

    Args:
        idx: (..., R, K) int indices.
        keep: (..., R, K) bool which entries belong to the set.
    """
    k = idx.shape[-1]
    # Each kept entry's place among the kept ones; the others go to a spare column K.
    place = np.where(keep, np.cumsum(keep, axis=-1) - 1, k)  # (..., R, K)
    n_rows = math.prod(keep.shape[:-1])
    out = np.zeros((n_rows, k + 1), np.int64)
    out[np.arange(n_rows)[:, None], place.reshape(n_rows, k)] = idx.reshape(n_rows, k)
    mask = np.arange(k) < keep.sum(axis=-1, keepdims=True)
    return out[:, :k].reshape(idx.shape), mask


def _f32(a: np.ndarray) -> np.ndarray:
    """float32 copy clipped to the documented feature range."""
    return np.minimum(np.maximum(a, -FEATURE_CLIP), FEATURE_CLIP).astype(np.float32)
