"""What PSAR reads off the state: the CAV slots and the obstacles around them, found once.

Every rule block (lane-change checks, car following of each horizon) reads
these same arrays, so the blocks agree on which vehicle is "the leader".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from diacc.envs.safety import (
    SAME_COL,
    PairKinematics,
    lane_end_kinematics,
    lane_leaders_followers,
    pair_kinematics,
)
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, flat_offsets, stack_last, take, take_last

#: Lateral drift (m) off its lane's centre line towards the ego lane from which a
#: neighbouring-lane vehicle counts as cutting in (both backends keep vehicles on the
#: centre line exactly unless they change lanes).
CUT_IN_DRIFT_M = 0.05


@dataclass(frozen=True)
class Cavs:
    """The CAV slots' own values, gathered once from the state."""

    state: TrafficState
    index: np.ndarray  # (..., C) vehicle index of each slot
    active: np.ndarray  # (..., C) bool on the road
    lane: np.ndarray  # (..., C) int64
    speed_mps: np.ndarray  # (..., C) longitudinal speed v |cos(heading)|

    @classmethod
    def of(cls, state: TrafficState, cav_index: np.ndarray) -> Cavs:
        return cls(
            state=state,
            index=cav_index,
            active=take(state.active, cav_index),
            lane=take(state.lane, cav_index).astype(np.int64),
            speed_mps=take(state.speed_mps, cav_index)
            * np.abs(np.cos(take(state.heading_rad, cav_index))),
        )

    @property
    def shape(self) -> tuple[int, ...]:
        """(..., C)"""
        return self.index.shape


@dataclass(frozen=True)
class Obstacles:
    """Each CAV's neighbours and walls, as the lane-change checks and car following read them.

    Vehicle indices are -1 where there is none (the kinematics are then not ``valid``).
    The target lane is the one the (possibly refused) action changes into; for an
    action that keeps the lane it is the own lane.
    """

    tf_vehicle: PairKinematics  # (..., C) the target lane's front vehicle
    tf_index: np.ndarray  # (..., C)
    tr_vehicle: PairKinematics  # (..., C) the target lane's rear vehicle
    tr_index: np.ndarray  # (..., C)
    sf_vehicle: PairKinematics  # (..., C) same-lane leader
    sf_index: np.ndarray  # (..., C)
    merging: PairKinematics  # (..., C) a vehicle ahead moving across into the lane
    merging_index: np.ndarray  # (..., C) (:func:`cut_in_front`)
    target_wall: PairKinematics  # (..., C) the end of the target lane (with its queue)
    own_wall: PairKinematics  # (..., C) the end of the own lane (with its queue)
    joining_rear: PairKinematics  # (..., C) a vehicle behind moving across into the
    joining_rear_index: np.ndarray  # (..., C) target lane (:func:`joining_target`)
    joining_front: PairKinematics  # (..., C) a vehicle ahead moving across into the
    joining_front_index: np.ndarray  # (..., C) target lane from the lane beyond


def find_obstacles(cavs: Cavs, offset: np.ndarray, road: Map, queue_gap_m: float) -> Obstacles:
    """The :class:`Obstacles` of CAVs moving ``offset`` (..., C) lanes (+1 left, -1 right)."""
    state, cav_index = cavs.state, cavs.index
    neighbours = lane_leaders_followers(state, cav_index, check=False)  # (..., C, 3)
    col = (offset + 1)[..., None]  # (..., C, 1) column of the target lane in LaneNeighbours
    pairs = stack_last(
        [
            take_last(neighbours.front, col)[..., 0],
            take_last(neighbours.rear, col)[..., 0],
            neighbours.front[..., SAME_COL],
        ],
    )  # (..., C, 3): target-lane front j, target-lane rear k, same-lane front j
    cut_in = cut_in_front(state, cav_index, road)  # (..., C)
    joining = joining_target(state, cav_index, offset, road)  # (..., C, 2): behind, ahead
    # One call per kind of obstacle (the formulas are elementwise): the three neighbours,
    # the vehicle cutting in and those joining the target lane behind and ahead as
    # columns, the target and own lanes' ends side by side.
    others = np.concatenate([pairs, cut_in[..., None], joining], -1)  # (..., C, 6)
    # checked slots, found neighbours; the ego column broadcasts against the four others
    kin = pair_kinematics(state, cav_index[..., None], others, check=False)
    n_cav = cav_index.shape[-1]
    walls = lane_end_kinematics(
        state,
        np.concatenate([cav_index, cav_index], -1),
        np.concatenate([cavs.lane + offset, cavs.lane], -1),
        road,
        queue_gap_m,
    )  # (..., 2C)
    return Obstacles(
        tf_vehicle=kin.column(0),
        tf_index=pairs[..., 0],
        tr_vehicle=kin.column(1),
        tr_index=pairs[..., 1],
        sf_vehicle=kin.column(2),
        sf_index=pairs[..., 2],
        merging=kin.column(3),
        merging_index=cut_in,
        target_wall=walls.column(slice(None, n_cav)),
        own_wall=walls.column(slice(n_cav, None)),
        joining_rear=kin.column(4),
        joining_rear_index=joining[..., 0],
        joining_front=kin.column(5),
        joining_front_index=joining[..., 1],
    )


def _drifting_toward(state: TrafficState, lane: np.ndarray, road: Map) -> np.ndarray:
    """(..., C, V) each vehicle moving across into ``lane`` (..., C) from a neighbouring
    lane: off its centre line towards it by more than :data:`CUT_IN_DRIFT_M`."""
    drift_m = state.y_m - road.lane_center_y_m(state.lane)  # (..., V) + = to the left
    side = state.lane[..., None, :] - lane[..., None]  # (..., C, V)
    return ((side == 1) & (drift_m[..., None, :] < -CUT_IN_DRIFT_M)) | (
        (side == -1) & (drift_m[..., None, :] > CUT_IN_DRIFT_M)
    )


def joining_target(
    state: TrafficState, cav_index: np.ndarray, offset: np.ndarray, road: Map
) -> np.ndarray:
    """(..., C, 2) the nearest vehicle behind (column 0) and ahead of (column 1) each CAV
    that is moving across into the lane its lane change ``offset`` (..., C) goes to, -1
    if none or no change.

    The target lane's rear and front vehicles are found by the lane each vehicle's
    centre is in; one whose change into that lane is under way still counts in its old
    lane. On SUMO a standing CAV moved right into such a human's path: the human, 12 m
    back at 18 m/s and half-way over from the lane beyond, hit it (issue 57); and a CAV
    at 10.5 m/s moved into a lane a standing human 10 m ahead was moving into from the
    other side (issue 60). The lane-change checks give them the target lane's rear and
    front tests (:mod:`diacc.envs.psar.lane_change`).
    """
    if not np.any(offset):  # no lane change asked: skip the (..., C, V) search
        return np.full((*cav_index.shape, 2), -1, np.int64)
    target = take(state.lane, cav_index).astype(np.int64) + offset  # (..., C)
    dx_m = state.x_m[..., None, :] - take(state.x_m, cav_index)[..., None]  # (..., C, V)
    candidate = (
        _drifting_toward(state, target, road)
        & state.active[..., None, :]
        & (offset != 0)[..., None]
    )  # (..., C, V)
    ahead = dx_m >= 0.0
    dist_m = np.stack(
        [np.where(candidate & ~ahead, -dx_m, np.inf), np.where(candidate & ahead, dx_m, np.inf)],
        -1,
    )  # (..., C, V, 2)
    nearest = np.argmin(dist_m, axis=-2)  # (..., C, 2)
    return np.where(np.isfinite(np.min(dist_m, axis=-2)), nearest, -1)


def cut_in_front(state: TrafficState, cav_index: np.ndarray, road: Map) -> np.ndarray:
    """(..., C) the nearest vehicle ahead of each CAV that is moving across into its
    lane from a neighbouring one (drift > :data:`CUT_IN_DRIFT_M`), -1 if none.

    Every vehicle is a candidate, not only the nearest one of each neighbouring
    lane: a merging HDV is often a queue's head with others alongside the CAV.
    """
    toward = _drifting_toward(state, take(state.lane, cav_index).astype(np.int64), road)
    dx_m = state.x_m[..., None, :] - take(state.x_m, cav_index)[..., None]  # (..., C, V)
    candidate = toward & (dx_m >= 0) & state.active[..., None, :]
    dx_m = np.where(candidate, dx_m, np.inf)
    nearest = np.argmin(dx_m, axis=-1)  # (..., C)
    return np.where(np.isfinite(np.min(dx_m, axis=-1)), nearest, -1)


def slot_of(state: TrafficState, cav_index: np.ndarray) -> np.ndarray:
    """(..., V) the agent slot of each vehicle (-1: an HDV, or a CAV without a slot)."""
    slots = np.full(state.x_m.shape, -1, np.int64)
    flat = cav_index + flat_offsets(cav_index.shape[:-1], state.n_vehicles, 1)  # into (E * V,)
    # Repeated vehicles (empty slots): the last slot wins.
    slots.reshape(-1)[flat] = np.broadcast_to(np.arange(cav_index.shape[-1]), flat.shape)
    return slots


class Margins(Protocol):
    """What the rule blocks ask of a horizon (:mod:`diacc.envs.psar.horizons`): the
    distances it adds to Algorithm 1's, each (..., C) or broadcasting."""

    def front_margin_m(
        self, kin: PairKinematics, action: np.ndarray, front_is_cav: np.ndarray | None = None
    ) -> np.ndarray: ...

    def rear_margin_m(self, rear_index: np.ndarray) -> np.ndarray | float: ...

    def clash_margin_m(self, speed_i_mps: np.ndarray, speed_j_mps: np.ndarray): ...

    def holds_short(self, front: PairKinematics, gap_m: np.ndarray) -> np.ndarray | bool: ...
