"""Safety geometry on a TrafficState: lane neighbours, gap/TTC, and the metrics' events.

PSAR (:mod:`diacc.envs.psar`) and the event detectors below both measure traffic
with these functions, so a "risk" means the same to the filter and to the
metrics. Everything here reads :class:`~diacc.sim.state.TrafficState` arrays
only, so it works the same for every backend, and is vectorised over
vehicles (a ``(Q, 3, V)`` masked matrix for the neighbour search), never a
Python loop over vehicles. A batch of states ((E, V) arrays) is handled by
the same code: index arrays then carry the leading env axis too, and all
pairwise work stays within each env.

Gap and TTC (paper, PSAR section)
-------------------------------------------
For an ego ``i`` and another vehicle ``j``::

    d_long = (x_j - x_i - L_veh) cos(theta_i) - W_i / 2 |sin(theta_i)|
    dv_long = v_i |cos(theta_i)| - v_j |cos(theta_j)|
    TTC = d_long / dv_long

* ``L_veh = (length_i + length_j) / 2``: positions are vehicle *centres*, so
  centre distance minus both half lengths is the bumper-to-bumper gap (the
  paper's ``L_veh`` for two vehicles of equal length).
* Sign convention: ``d_long`` is *signed*, positive when ``j`` is ahead
  (``x_j >= x_i``) and negative when ``j`` is behind. For a vehicle behind,
  the formula is applied with the roles of the two positions swapped and the
  sign flipped, ``d_long = -[(x_i - x_j - L_veh) cos(theta_i) - W_i/2
  |sin(theta_i)|]``, so ``|d_long|`` is the bumper gap either way (with the
  ego's heading and width, the ego being the one that manoeuvres).
* With a signed gap the paper's TTC needs no special case: a front vehicle
  is approached when the ego is faster (``d > 0``, ``dv > 0``); a rear vehicle
  approaches the ego when it is faster (``d < 0``, ``dv < 0``). Both give a
  positive TTC. ``TTC <= 0`` or ``dv_long == 0`` means "not closing" and is
  reported as ``+inf``; so ``ttc_s < inf`` is the paper's ``TTC > 0``.
* ``Risk(d0, t0) := |d_long| <= d0 and 0 < TTC <= t0``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.config import EventConfig
from diacc.errors import DiaccError
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, on_road_window, take, take_last


class SafetyError(DiaccError, ValueError):
    """Bad input to a safety function (wrong shape, unknown action...); one line."""


#: Lane offsets searched by :func:`lane_leaders_followers`, in column order.
LANE_OFFSETS = (-1, 0, +1)
RIGHT_COL, SAME_COL, LEFT_COL = 0, 1, 2


# --------------------------------------------------------------------------
# Neighbour search
# --------------------------------------------------------------------------
@dataclass
class LaneNeighbours:
    """Nearest vehicles ahead and behind in the right / same / left lane.

    Columns follow :data:`LANE_OFFSETS` (right, same, left). ``-1`` = none.
    """

    front: np.ndarray  # (..., Q, 3) int64, vehicle index of the nearest vehicle ahead
    rear: np.ndarray  # (..., Q, 3) int64, vehicle index of the nearest vehicle behind


def lane_leaders_followers(
    state: TrafficState, query: np.ndarray, check: bool = True
) -> LaneNeighbours:
    """Find each query vehicle's nearest front and rear vehicle in three lanes.

    Candidates are active vehicles other than the query vehicle whose absolute
    lane is ``lane[q] + offset`` for ``offset`` in (-1, 0, +1). "Front" means
    ``x_j >= x_q`` (a vehicle exactly alongside counts as front, because for a
    lane change it is the one the ego would cut into); "rear" means
    ``x_j < x_q``. Ties in distance go to the lowest vehicle index, so the
    result is deterministic. Inactive query vehicles get the same treatment
    (their neighbours are still found); callers mask them.

    Args:
        state: Traffic state (a batch).
        query: (..., Q) vehicle indices.
        check: validate ``query`` (callers that made it themselves skip the cost).

    Returns:
        :class:`LaneNeighbours` with (..., Q, 3) index arrays.
    """
    query = check_indices(state, query, "query") if check else np.asarray(query, np.int64)
    offsets = np.asarray(LANE_OFFSETS, dtype=np.int64)  # (3,)
    lane = state.lane.astype(np.int64)  # (..., V)
    target_lane = take(lane, query)[..., None] + offsets  # (..., Q, 3)
    dx_m = state.x_m[..., None, :] - take(state.x_m, query)[..., None]  # (..., Q, V)
    others = state.active[..., None, :] & (
        np.arange(state.n_vehicles) != query[..., None]
    )  # (..., Q, V)
    in_lane = (lane[..., None, None, :] == target_lane[..., None]) & others[
        ..., None, :
    ]  # (..., Q, 3, V)
    ahead = (dx_m >= 0.0)[..., None, :]  # (..., Q, 1, V)
    front_dist = np.where(in_lane & ahead, dx_m[..., None, :], np.inf)  # (..., Q, 3, V)
    rear_dist = np.where(in_lane & ~ahead, -dx_m[..., None, :], np.inf)  # (..., Q, 3, V)
    return LaneNeighbours(front=_argmin_or_none(front_dist), rear=_argmin_or_none(rear_dist))


def same_lane_leaders(state: TrafficState) -> np.ndarray:
    """(..., V) each vehicle's same-lane leader, -1: none.

    What :func:`lane_leaders_followers` gives in its same-lane front column
    for every vehicle as the query (the same candidates, distances and
    ties), searched in that lane alone: the event detectors need no other.
    """
    lane = state.lane
    dx_m = state.x_m[..., None, :] - state.x_m[..., None]  # (..., V, V) x_j - x_i
    n = state.n_vehicles
    candidate = (
        state.active[..., None, :]
        & (lane[..., None, :] == lane[..., None])
        & ~np.eye(n, dtype=bool)
        & (dx_m >= 0.0)
    )  # (..., V, V)
    return _argmin_or_none(np.where(candidate, dx_m, np.inf))


def _argmin_or_none(dist: np.ndarray) -> np.ndarray:
    """Index of the smallest finite entry along the last axis, -1 if all inf."""
    if dist.shape[-1] == 0:
        return np.full(dist.shape[:-1], -1, dtype=np.int64)
    idx = np.argmin(dist, axis=-1)  # (Q, 3)
    found = np.isfinite(take_last(dist, idx[..., None])[..., 0])
    return np.where(found, idx, -1).astype(np.int64)


# --------------------------------------------------------------------------
# Gap and TTC
# --------------------------------------------------------------------------
@dataclass
class PairKinematics:
    """Gap, closing speed and TTC of ego/other pairs (see module docstring)."""

    valid: np.ndarray  # (...) bool, the other vehicle exists (index >= 0)
    d_long_m: np.ndarray  # (...) float64, signed gap, + ahead / - behind; nan if not valid
    dv_long_mps: np.ndarray  # (...) float64, v_i|cos th_i| - v_j|cos th_j|; nan if not valid
    ttc_s: np.ndarray  # (...) float64, > 0 when closing, +inf otherwise or if not valid

    def column(self, k: int | slice) -> PairKinematics:
        """The pairs in column ``k`` (last axis; a slice keeps the axis)."""
        return PairKinematics(*(a[..., k] for a in _fields(self)))

    def nearer(self, other: PairKinematics) -> PairKinematics:
        """Elementwise the pair with the smaller signed gap (for fronts: the nearer obstacle)."""
        with np.errstate(invalid="ignore"):
            take = other.valid & (~self.valid | (other.d_long_m < self.d_long_m))
        return PairKinematics(
            *(np.where(take, b, a) for a, b in zip(_fields(self), _fields(other), strict=True))
        )

    def risk(self, d0_m: float, t0_s: float) -> np.ndarray:
        """Paper's ``Risk(d0, t0)``: ``|d_long| <= d0 and 0 < TTC <= t0`` (False if absent)."""
        with np.errstate(invalid="ignore"):
            return self.valid & (np.abs(self.d_long_m) <= d0_m) & (self.ttc_s <= t0_s)


def _fields(kin: PairKinematics) -> tuple[np.ndarray, ...]:
    return kin.valid, kin.d_long_m, kin.dv_long_mps, kin.ttc_s


def lane_end_kinematics(
    state: TrafficState, ego: np.ndarray, lane: np.ndarray, road: Map, queue_gap_m: float
) -> PairKinematics:
    """The end of ``lane`` ahead of each ego as a standing obstacle (valid where it ends).

    Same formulas as :func:`pair_kinematics` with the other vehicle replaced
    by a wall of zero length and speed: a CAV in a lane that ends, or
    changing into one, must be able to stop before its end. The wall stands
    in front of the queue that will form there: every vehicle between the
    ego and the lane end in that lane moves it back by its length plus
    ``queue_gap_m``, because none of them can pass the end either. (A
    leader slowing down for the lane end is otherwise seen too late: its
    braking grows as it nears the end.)
    """
    ego = np.asarray(ego, dtype=np.int64)  # (..., C)
    lane = np.minimum(np.maximum(np.asarray(lane, dtype=np.int64), 0), road.max_lanes - 1)
    ego_x_m = take(state.x_m, ego)
    end_x_m = road.lane_end_m()[take(state.segment, ego).astype(np.int64), lane]  # inf if none
    queued = (
        state.active[..., None, :]
        & (state.lane[..., None, :] == lane[..., None])
        & (state.x_m[..., None, :] > ego_x_m[..., None])
        & (state.x_m[..., None, :] < end_x_m[..., None])
    )  # (..., C, V)
    queue_m = np.where(queued, (state.length_m + queue_gap_m)[..., None, :], 0.0).sum(-1)
    end_x_m = end_x_m - queue_m  # (..., C)
    valid = np.isfinite(end_x_m)
    heading_i = take(state.heading_rad, ego)
    cos_i = np.cos(heading_i)
    side_i_m = 0.5 * take(state.width_m, ego) * np.abs(np.sin(heading_i))
    gap_m = (end_x_m - ego_x_m - 0.5 * take(state.length_m, ego)) * cos_i - side_i_m
    dv_long_mps = take(state.speed_mps, ego) * np.abs(cos_i)
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc_raw_s = gap_m / dv_long_mps
    closing = valid & (dv_long_mps > 0.0) & (ttc_raw_s > 0.0)
    return PairKinematics(
        valid=valid,
        d_long_m=np.where(valid, gap_m, np.nan),
        dv_long_mps=np.where(valid, dv_long_mps, np.nan),
        ttc_s=np.where(closing, ttc_raw_s, np.inf),
    )


def pair_kinematics(
    state: TrafficState, ego: np.ndarray, other: np.ndarray, check: bool = True
) -> PairKinematics:
    """Paper's ``d_long``, ``dv_long`` and TTC for pairs (ego[k], other[k]).

    Args:
        state: Traffic state (a batch).
        ego: vehicle indices (leading env axes of a batch, then any shape), all valid.
        other: vehicle indices of the same shape; ``-1`` marks "no vehicle".
        check: validate the indices (callers that made them themselves skip the cost;
            unchecked, ``ego`` may also be any shape that broadcasts against ``other``).

    Returns:
        :class:`PairKinematics` of that shape.
    """
    ego = np.asarray(ego, dtype=np.int64)
    other = np.asarray(other, dtype=np.int64)
    if check:
        if ego.shape != other.shape:
            raise SafetyError(f"ego shape {ego.shape} differs from other shape {other.shape}")
        lead = state.x_m.shape[:-1]
        check_indices(state, ego.reshape(lead + (-1,)), "ego")
        if np.any((other < -1) | (other >= state.n_vehicles)):
            raise SafetyError(f"other indices must be -1 or in [0, {state.n_vehicles})")
    valid = other >= 0
    j = np.where(valid, other, 0)  # safe gather index
    heading_i = take(state.heading_rad, ego)
    cos_i = np.cos(heading_i)
    side_i_m = 0.5 * take(state.width_m, ego) * np.abs(np.sin(heading_i))
    half_lengths_m = 0.5 * (take(state.length_m, ego) + take(state.length_m, j))  # L_veh
    dx_m = take(state.x_m, j) - take(state.x_m, ego)
    ahead = dx_m >= 0.0
    gap_m = (np.abs(dx_m) - half_lengths_m) * cos_i - side_i_m  # bumper gap, ego frame
    d_long_m = np.where(ahead, gap_m, -gap_m)
    dv_long_mps = take(state.speed_mps, ego) * np.abs(cos_i) - take(state.speed_mps, j) * np.abs(
        np.cos(take(state.heading_rad, j))
    )
    # A closing speed of ~1e-308 overflows to inf: that TTC is "never", as wanted.
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ttc_raw_s = d_long_m / dv_long_mps
    closing = valid & (dv_long_mps != 0.0) & (ttc_raw_s > 0.0)
    return PairKinematics(
        valid=valid,
        d_long_m=np.where(valid, d_long_m, np.nan),
        dv_long_mps=np.where(valid, dv_long_mps, np.nan),
        ttc_s=np.where(closing, ttc_raw_s, np.inf),
    )


# --------------------------------------------------------------------------
# PSAR (paper Algorithm 1)
# --------------------------------------------------------------------------
# --------------------------------------------------------------------------
# Event detectors for metrics
# --------------------------------------------------------------------------
@dataclass
class SafetyEvents:
    """Safety-critical events of one state, per vehicle (False for inactive ones)."""

    small_gap: np.ndarray  # (V,) bool bumper gap to same-lane leader < sce_min_gap_m
    low_ttc: np.ndarray  # (V,) bool TTC to same-lane leader < sce_ttc_s
    collision: np.ndarray  # (V,) bool in a collision pair this step
    emergency_brake: np.ndarray  # (V,) bool accel_mps2 < -emergency_decel_mps2

    @property
    def any(self) -> np.ndarray:
        """(V,) bool: at least one safety-critical event."""
        return self.small_gap | self.low_ttc | self.collision | self.emergency_brake


def waiting_events(state: TrafficState, cfg: EventConfig) -> np.ndarray:
    """(V,) bool: active vehicles slower than ``waiting_speed_mps`` (paper: 3 m/s)."""
    return state.active & (state.speed_mps < cfg.waiting_speed_mps)


def safety_critical_events(state: TrafficState, cfg: EventConfig) -> SafetyEvents:
    """Detect safety-critical events (paper p(SCE)) for every vehicle.

    Gap and TTC use :func:`pair_kinematics` to the same-lane leader (its
    ``d_long`` is the bumper gap when headings are 0). A collision counts
    even if the backend removed the vehicle in the same step.
    """
    # Only vehicles on the road have events or leaders: search their window alone.
    lo, hi = on_road_window(state.active)
    part = state if hi - lo == state.n_vehicles else state.vehicles(lo, hi)
    everyone = np.broadcast_to(np.arange(hi - lo), part.x_m.shape)  # (..., W)
    leader = same_lane_leaders(part)  # (..., W)
    kin = pair_kinematics(part, everyone, leader, check=False)  # indices made here
    small_gap, low_ttc = np.zeros((2,) + state.x_m.shape, bool)  # (..., V) each
    with np.errstate(invalid="ignore"):
        small_gap[..., lo:hi] = part.active & kin.valid & (kin.d_long_m < cfg.sce_min_gap_m)
    low_ttc[..., lo:hi] = part.active & (kin.ttc_s < cfg.sce_ttc_s)
    return SafetyEvents(
        small_gap=small_gap,
        low_ttc=low_ttc,
        collision=state.collided,
        emergency_brake=state.active & (state.accel_mps2 < -cfg.emergency_decel_mps2),
    )


# --------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------
def check_indices(state: TrafficState, idx: np.ndarray, name: str) -> np.ndarray:
    """``idx`` as int64 vehicle indices of ``state``; :class:`SafetyError` if it is not one.

    One index axis after the state's env axis: (E, Q).
    """
    arr = np.asarray(idx)
    lead = state.x_m.shape[:-1]
    if arr.ndim != len(lead) + 1 or arr.shape[:-1] != lead:
        raise SafetyError(f"{name} must be a 1-D index array per env, got shape {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise SafetyError(f"{name} must hold integer vehicle indices, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    if np.any((arr < 0) | (arr >= state.n_vehicles)):
        raise SafetyError(f"{name} holds indices outside [0, {state.n_vehicles})")
    return arr
