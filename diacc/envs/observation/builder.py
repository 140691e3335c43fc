"""The observation builder: a stream of TrafficStates -> actor observations and critic state.

The builder only reads :class:`~diacc.sim.state.TrafficState` arrays and the
:class:`~diacc.sim.maps.Map`; it never knows which backend produced the state.
It keeps the history and the neighbour sets of the current instant and
composes feature functions (:mod:`~diacc.envs.observation.actor_features`,
:mod:`~diacc.envs.observation.critic_features`) into the layout's containers
(:mod:`~diacc.envs.observation.layout`). Which functions: :func:`features_for`,
the one place the config's options pick them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from diacc.config import ObservationConfig
from diacc.envs.lateral_frame import agent_map, is_mirrored, mirror_state
from diacc.envs.observation.actor_features import (
    Context,
    Slots,
    ego_lane_features,
    memory_features,
    neighbour_features,
    road_features,
    self_features,
)
from diacc.envs.observation.critic_features import (
    on_road_rows,
    road_state_features,
    route_lane_features,
    traffic_features,
    traffic_features_no_clock,
    vehicle_rows,
)
from diacc.envs.observation.frames import Frame, History, nearest_neighbours
from diacc.envs.observation.layout import (
    ActorObs,
    CriticState,
    ObservationError,
    ObservationSpec,
    check_road,
)
from diacc.envs.observation.scales import (
    MapScales,
    SegmentColumn,
    segment_present,
    segment_speed_limit,
)
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState

#: An actor feature: (context, frame, CAV slots) -> some :class:`ActorObs` fields.
ActorFeature = Callable[[Context, Frame, Slots], dict]
#: A critic feature: (context, frame) -> some :class:`CriticState` fields.
CriticFeature = Callable[[Context, Frame], dict]


@dataclass(frozen=True)
class Features:
    """The feature functions a builder composes; together they fill every field once."""

    actor: tuple[ActorFeature, ...]
    critic: tuple[CriticFeature, ...]
    road_column: SegmentColumn  # the road table's fourth column


def features_for(cfg: ObservationConfig, compact_critic: bool = False) -> Features:
    """The features of the config's options: the one place they are read.

    ``road_speed_limits``: the road table's fourth column is each segment's speed
    limit, else 1; ``critic_step_input``: the critic's traffic features carry the
    clock, else 0; ``compact_critic`` (the env sets it for demand scenarios): the
    critic's rows hold the vehicles on the road first, else row i is vehicle i.
    ``lateral_frame`` is not a feature: the whole state is observed mirrored
    (:mod:`diacc.envs.lateral_frame`).
    """
    return Features(
        actor=(
            self_features,
            neighbour_features,
            ego_lane_features,
            road_features,
            memory_features,
        ),
        critic=(
            on_road_rows if compact_critic else vehicle_rows,
            route_lane_features,
            road_state_features,
            traffic_features if cfg.critic_step_input else traffic_features_no_clock,
        ),
        road_column=segment_speed_limit if cfg.road_speed_limits else segment_present,
    )


class ObservationBuilder:
    """Turns the stream of TrafficStates of one episode into actor/critic inputs.

    Call :meth:`reset` with the first state of an episode, :meth:`push` with
    every following state, then :meth:`actor` and :meth:`critic` for the
    current (last pushed) state. Per-step work is vectorised over vehicles:
    one (V, V) distance table per step serves both the actor's and the
    critic's neighbour sets, which keeps the two consistent by construction.

    The stream is a batch's states (E, V) (E = 1 for one env): every array has
    the leading env axis, :meth:`reset_rows` restarts single envs and the
    results are those of E builders (the step of
    :class:`diacc.envs.batch.EnvBatch`).
    """

    def __init__(
        self,
        road: Map,
        cfg: ObservationConfig,
        episode_steps: int,
        compact_critic: bool = False,
        features: Features | None = None,
    ) -> None:
        """``compact_critic``: the critic's rows hold the vehicles on the road first
        (:func:`features_for`; the env sets it for demand scenarios). ``features``:
        other feature functions of the same layout (default: :func:`features_for`)."""
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
        self.features = features or features_for(cfg, compact_critic)
        self._spec = ObservationSpec.from_config(cfg)
        self._ctx = Context(MapScales.of(road, self.features.road_column), cfg, self.episode_steps)
        self._frame: Frame | None = None

    def spec(self) -> ObservationSpec:
        """Sizes of this builder's observations (:class:`ObservationSpec`)."""
        return self._spec

    # ---- state stream ------------------------------------------------------
    def reset(self, state: TrafficState) -> None:
        """Start an episode: the whole history holds copies of ``state``."""
        self._check_state(state, expect_vehicles=None)
        state = self._in_frame(state)
        self._frame = Frame(state, History.filled(state, self.cfg.history_steps))

    def reset_rows(self, rows: np.ndarray, state: TrafficState) -> None:
        """Envs ``rows`` of a batch start new episodes: ``state`` is the whole (E, V) batch
        with those rows' first states; their histories are refilled, the others kept."""
        if self._frame is None:
            raise ObservationError("reset_rows() called before reset(); start the batch first")
        self._check_state(state, expect_vehicles=self._frame.state.n_vehicles)
        state = self._in_frame(state)
        self._frame.hist.fill_rows(rows, state)
        self._frame = Frame(state, self._frame.hist)

    def push(self, state: TrafficState) -> None:
        """Append the state of a new step (a batch, as the one :meth:`reset` had);
        the oldest history entry drops out."""
        if self._frame is None:
            raise ObservationError("push() called before reset(); start the episode first")
        self._check_state(state, expect_vehicles=self._frame.state.n_vehicles)
        state = self._in_frame(state)
        self._frame.hist.push(state)
        self._frame = Frame(state, self._frame.hist)

    @property
    def neighbours(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, K) int64 neighbour indices and (V, K) bool mask of the current state."""
        frame = self._require_frame()
        return frame.nbr, frame.nbr_mask

    # ---- observations --------------------------------------------------------
    def actor(
        self,
        cav_index: np.ndarray,
        action_memory: np.ndarray,
        last_refined_action: np.ndarray,
    ) -> ActorObs:
        """Observations of the CAV slots ``cav_index`` for the current state.

        Args:
            cav_index: (..., C) vehicle indices of the CAV slots, fixed for the episode;
                ``...`` is the state's leading (env) axes.
            action_memory: (..., C, 2) int64 proposed and PSAR-refined action of the
                previous step per slot; copied into the observation.
            last_refined_action: (..., V) int64 refined action each vehicle executed at
                the previous step (only CAV entries are read).
        """
        return self._actor(self._require_frame(), cav_index, action_memory, last_refined_action)

    def critic(self) -> CriticState:
        """Global state of the current step, padded to ``max_vehicles``."""
        return self._critic(self._require_frame())

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
        sub = Frame(frame.state.rows(rows), frame.hist.rows(rows))
        sub.searched(self.cfg.n_neighbours)
        return self._actor(sub, cav_index, action_memory, last_refined_action), self._critic(sub)

    # ---- internals -----------------------------------------------------------
    def _actor(self, frame: Frame, cav_index, action_memory, last_refined_action) -> ActorObs:
        """:meth:`actor` of a frame with any leading (env) axes ``...``."""
        state = frame.state
        slots = Slots.of(
            state, *self._checked_slots(state, cav_index, action_memory, last_refined_action)
        )
        fields: dict[str, np.ndarray] = {}
        for feature in self.features.actor:
            fields.update(feature(self._ctx, frame, slots))
        return ActorObs(**fields)

    def _critic(self, frame: Frame) -> CriticState:
        """:meth:`critic` of a frame with any leading (env) axes ``...``."""
        fields: dict[str, np.ndarray] = {}
        for feature in self.features.critic:
            fields.update(feature(self._ctx, frame))
        return CriticState(**fields)

    def _neighbours(self, state: TrafficState) -> tuple[np.ndarray, np.ndarray]:
        """(..., V, K) neighbour sets of ``state`` (:func:`~.frames.nearest_neighbours`)."""
        return nearest_neighbours(state, self.cfg.n_neighbours)

    def _in_frame(self, state: TrafficState) -> TrafficState:
        """A copy of ``state`` in the agents' frame (mirrored or as it is)."""
        return mirror_state(state, self.road) if self.mirrored else state.copy()

    def _current(self) -> Frame:
        if self._frame is None:
            raise ObservationError("no state yet; call reset() with the first state")
        return self._frame

    def _require_frame(self) -> Frame:
        """The current frame with its neighbour sets."""
        return self._current().searched(self.cfg.n_neighbours)

    @staticmethod
    def _checked_slots(state: TrafficState, cav_index, action_memory, last_refined_action):
        """The :meth:`actor` arguments as arrays, or a one-line :class:`ObservationError`."""
        lead, n_veh = state.x_m.shape[:-1], state.n_vehicles
        cav_index = np.asarray(cav_index)
        if (
            cav_index.ndim != len(lead) + 1
            or cav_index.shape[:-1] != lead
            or not np.issubdtype(cav_index.dtype, np.integer)
        ):
            raise ObservationError(
                f"cav_index must be an integer array of shape (..., C) after the state's "
                f"leading axes {lead}, got {cav_index!r}"
            )
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
        return cav_index, action_memory, last_refined_action

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
