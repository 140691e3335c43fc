"""PSAR, the paper's Algorithm 1: the safety filter between the actor and the simulator.

The actor proposes one action per CAV; :func:`psar` refines it with four
rules (Cancel-LC, Decel-LC, Force-Brake, Suppress-Accel) from the gaps and
TTCs of :mod:`diacc.safety`, and reports which rules took effect
(:class:`PSARResult`), which the metrics and the training logs count
(:func:`rule_counts`). Options and thresholds: :class:`~diacc.config.PSARConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.actions import (
    ACCELERATE,
    ACTION_LANE_OFFSET,
    ACTION_NAMES,
    DECELERATE,
    LANE_LEFT,
    LANE_RIGHT,
    REMAIN,
    action_speed_change_mps,
    lane_change_allowed,
)
from diacc.config import PSARConfig, SimConfig
from diacc.kinematics import safe_gap_m
from diacc.maps import Map
from diacc.safety import (
    SAME_COL,
    PairKinematics,
    SafetyError,
    check_indices,
    lane_end_kinematics,
    lane_leaders_followers,
    pair_kinematics,
)
from diacc.state import TrafficState, take

#: Rule codes of :attr:`PSARResult.rule`.
RULE_NONE, CANCEL_LC, DECEL_LC, FORCE_BRAKE, SUPPR_ACCEL = 0, 1, 2, 3, 4
RULE_NAMES = ("none", "cancel_lc", "decel_lc", "force_brake", "suppr_accel")
#: Bit of each rule code in :attr:`PSARResult.rule_mask` (``1 << (code - 1)``).
RULE_BITS = {code: 1 << (code - 1) for code in range(1, len(RULE_NAMES))}
#: Lateral drift (m) off its lane's centre line towards the ego lane from which a
#: neighbouring-lane vehicle counts as cutting in (both backends keep vehicles on the
#: centre line exactly unless they change lanes).
CUT_IN_DRIFT_M = 0.05


@dataclass
class PSARResult:
    """Refined actions and what PSAR did, one entry per CAV slot.

    ``rule`` is the *last* refinement that took effect (the one that decided
    the final action); ``rule_mask`` has one bit per refinement that took
    effect (:data:`RULE_BITS`), which is what fire rates per rule should
    count. The only combination Algorithm 1 can produce is Cancel-LC followed
    by Force-Brake. A refinement "takes effect" only when it changes the
    outcome: Force-Brake on an action that already brakes at least as hard is
    not reported, and Decel-LC is reported only if the lane change survives
    the rear-vehicle check (its braking is then in ``decel_lc_mps2``).
    ``speed_change_mps`` is what the environment commands: the refined
    action's speed change, Decel-LC's braking and Force-Brake's magnitude
    folded into one number per CAV.
    """

    action: np.ndarray  # (C,) int64 refined action
    speed_change_mps: np.ndarray  # (C,) float64 commanded change of target speed over the step
    rule: np.ndarray  # (C,) int8 last rule code (RULE_*)
    rule_mask: np.ndarray  # (C,) int8 bitmask of the rules that took effect
    decel_lc_mps2: np.ndarray  # (C,) float64 Decel-LC braking b_lc >= 0 (0 = none)
    invalid_lc: np.ndarray  # (C,) bool proposed lane change that cannot be made here
    active: np.ndarray  # (C,) bool CAV on the road (inactive: action passed through)


def psar(
    state: TrafficState,
    cav_index: np.ndarray,
    proposed_action: np.ndarray,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig | None = None,
) -> PSARResult:
    """Refine the actor's actions with paper Algorithm 1, vectorised over CAVs.

    The algorithm is followed line by line; the choices it leaves open are:

    * Target lane = ego lane + 1 for ``left``, - 1 for ``right``. A lane
      change the road does not allow (:func:`lane_change_allowed`: the target
      lane is missing here or ends within the change's reach; the same rule
      the backends apply) is replaced by ``remain`` *before* Algorithm 1 and
      flagged in ``invalid_lc``, so the car-following checks still run;
      without this a policy could dodge them by asking for an impossible
      change.
    * Lane ends are standing obstacles: the front vehicle of the car-following
      block is the nearer of the same-lane leader and the end of the ego
      lane; the front vehicle of the lane-change checks is the nearer of the
      target-lane leader and the end of the target lane
      (:func:`lane_end_kinematics`).
    * ``cfg.coordinate_lane_changes`` (default on): of two CAVs changing into
      the same lane, or towards each other into adjacent lanes, closer than
      ``d_safe`` (plus the safe gap of the "stopping" horizon) along the
      road, the rear one is cancelled (Cancel-LC). Algorithm 1 is per agent
      and neither would see the other; connected CAVs know each other's
      intent. For the same reason a CAV does not change lanes next to an
      HDV alongside (within ``d_safe``) in the lane beyond the target
      lane, whose intent it cannot know.
    * Rear vehicle ``k``: the first cancel test ``|d_long| <= d_LC,min`` is
      evaluated on the rear bumper gap ``-d_long`` so that vehicles already
      overlapping alongside (gap < 0) also cancel; for every non-overlapping
      pair this equals the paper's ``|d_long|``.
    * Decel-LC: ``b_lc = min(|dv_long|, b_max)`` with the target-lane front
      vehicle, applied over the step of the lane change; returned in
      ``decel_lc_mps2``. It is zeroed if the change is then cancelled.
    * The car-following block (lines 17-27) uses the front obstacle in the
      ego's current lane, and runs for actions {remain, accelerate,
      decelerate} including lane changes cancelled above. Its second branch
      sets ``remain`` even if the proposal was ``decelerate`` (the gap is
      small but not closing), exactly as the pseudocode says.
    * Force-Brake magnitude (``cfg.force_brake``): ``"cancel"`` (default)
      lowers the target speed by ``max(dv_action, c + dv_action)`` for the
      distance trigger (line 19) and ``max(dv_action, c)`` for the TTC trigger
      (line 23), with ``c`` the closing speed and ``dv_action`` the
      decelerate action's step (the authors' own implementation), bounded by
      the CAV's planned braking ``sim.cav.safe_decel_mps2`` over the step;
      ``"paper"`` is the literal reading, action 4 = one ``dv_action`` step,
      which cannot stop a CAV that closes faster than that.
    * Horizon (``cfg.horizon``): ``"stopping"`` (default) lengthens d_warn and
      d_att, and the lane-change cancel distance d_LC,min to the target-lane
      front and rear vehicles, by Gipps' safe gap
      (:func:`~diacc.kinematics.safe_gap_m`): one decision step of reaction,
      then braking at the CAV's planned deceleration while the vehicle ahead
      brakes as hard (a rear HDV reacts at once, a rear CAV after a step).
      The authors' distances come from a 15 m/s road; at 25 m/s a CAV needs
      about 60 m to brake for a standing queue, and a leader that brakes
      hard needs about one second of headway. ``"paper"`` uses the fixed
      thresholds.
    * Cut-ins: the nearest vehicle ahead in a neighbouring lane whose
      centre has left its lane's centre line towards the ego lane by more
      than :data:`CUT_IN_DRIFT_M` (a lane change into the ego lane under
      way, :func:`_cut_in_front`) is a front obstacle of the car-following
      block too. Without it
      the CAV sees the merging vehicle only once its centre crosses the lane
      boundary; on SUMO, where an LC2013 driver may start a merge from
      standstill a few metres ahead of a CAV (its gap check assumes the CAV
      keeps its speed), the CAV would meanwhile accelerate into a gap it can
      no longer brake for (``bench --safety``: the heuristic on train-50,
      ``paper-congestion``, 330 steps).
    * Inactive CAVs keep their proposed action with rule NONE.

    A batch of states ((E, V) arrays, :class:`~diacc.state.TrafficState`) is
    filtered in one call with (E, C) slots and actions; every CAV only ever
    meets vehicles of its own env, and the results are those of E calls.

    Args:
        state: Traffic state the actions will be applied to (or a batch).
        cav_index: (..., C) vehicle indices of the CAV slots.
        proposed_action: (..., C) int actions in 0..4.
        cfg: PSAR thresholds and options.
        road: the :class:`~diacc.maps.Map`.
        sim: step length, action size and CAV braking limit (default
            :class:`~diacc.config.SimConfig`).

    Returns:
        :class:`PSARResult`.
    """
    sim = sim or SimConfig()
    cav_index = check_indices(state, cav_index, "cav_index")
    action = np.asarray(proposed_action)
    if action.shape != cav_index.shape:
        raise SafetyError(
            f"proposed_action shape {action.shape} differs from cav_index shape {cav_index.shape}"
        )
    if not np.issubdtype(action.dtype, np.integer):
        raise SafetyError(f"proposed_action must be integers, got dtype {action.dtype}")
    if np.any((action < 0) | (action >= len(ACTION_NAMES))):
        raise SafetyError(f"proposed_action must be in 0..{len(ACTION_NAMES) - 1}")
    if not isinstance(road, Map):
        raise SafetyError(f"road must be a Map, got {type(road).__name__}")
    seg = take(state.segment, cav_index).astype(np.int64)
    if np.any(seg >= len(road.segments)) or np.any(seg < 0):
        raise SafetyError(f"segment index outside the road's {len(road.segments)} segments")

    shape = cav_index.shape  # (..., C)
    step_s, dv_action = sim.step_s, sim.speed_change_mps
    safe_decel = sim.cav.safe_decel_mps2
    max_brake_mps = safe_decel * step_s  # largest planned speed drop within one step
    stopping = cfg.horizon == "stopping"
    active = take(state.active, cav_index)  # (..., C)
    proposed = action.astype(np.int64)
    a = proposed.copy()
    mask = np.zeros(shape, dtype=np.int8)
    neighbours = lane_leaders_followers(state, cav_index)  # (..., C, 3)

    ego_speed_mps = take(state.speed_mps, cav_index) * np.abs(
        np.cos(take(state.heading_rad, cav_index))
    )

    def front_margin_m(kin: PairKinematics, action: np.ndarray) -> np.ndarray:
        """Extra distance of the "stopping" horizon behind a front obstacle, 0 for "paper".

        Gipps' safe gap, with the speed the CAV reaches by the end of the step if
        it accelerates as proposed (braking proposals are judged at the current speed).
        """
        if not stopping:
            return np.zeros(shape)
        lead_speed_mps = ego_speed_mps - np.nan_to_num(kin.dv_long_mps)  # 0 for a wall
        end_speed_mps = ego_speed_mps + np.maximum(action_speed_change_mps(action, dv_action), 0)
        gap_m = safe_gap_m(ego_speed_mps, lead_speed_mps, step_s, safe_decel, end_speed_mps)
        return np.where(kin.valid, gap_m, 0.0)

    # ---- lane change the road does not allow -> remain ---------------------
    is_lc = active & ((a == LANE_LEFT) | (a == LANE_RIGHT))
    invalid_lc = is_lc & ~lane_change_allowed(state, cav_index, a, road, sim)
    a = np.where(invalid_lc, REMAIN, a)
    is_lc &= ~invalid_lc
    offset = ACTION_LANE_OFFSET[a]  # (..., C)
    lane = take(state.lane, cav_index).astype(np.int64)

    # ---- lines 2-16: lane-change checks on the target lane ----------------
    col = (offset + 1)[..., None]  # (..., C, 1) column of the target lane in LaneNeighbours
    pairs = np.stack(
        [
            np.take_along_axis(neighbours.front, col, -1)[..., 0],
            np.take_along_axis(neighbours.rear, col, -1)[..., 0],
            neighbours.front[..., SAME_COL],
        ],
        axis=-1,
    )  # (..., C, 3): target-lane front j, target-lane rear k, same-lane front j
    kin = pair_kinematics(state, np.broadcast_to(cav_index[..., None], pairs.shape), pairs)
    tf_vehicle, tr, sf_vehicle = (kin.column(k) for k in range(3))
    # Front obstacles: the leader, and the end of the lane (with its queue) as a wall.
    target_fronts = [
        tf_vehicle,
        lane_end_kinematics(state, cav_index, lane + offset, road, cfg.queue_gap_m),
    ]
    own_fronts = [sf_vehicle, lane_end_kinematics(state, cav_index, lane, road, cfg.queue_gap_m)]
    own_fronts.append(pair_kinematics(state, cav_index, _cut_in_front(state, cav_index, road)))

    cancel_front = np.zeros(shape, dtype=bool)
    b_lc_mps2 = np.zeros(shape)
    for tf in target_fronts:
        has_front = is_lc & tf.valid
        cancel = has_front & (
            (tf.d_long_m <= cfg.d_lc_min_m + front_margin_m(tf, a))
            | tf.risk(cfg.d_safe_m, cfg.ttc_safe_s)
        )
        decel = has_front & (
            tf.risk(cfg.d_safe_m, cfg.ttc_att_s) | tf.risk(cfg.d_att_m, cfg.ttc_safe_s)
        )
        cancel_front |= cancel
        b_lc_mps2 = np.where(
            decel,
            np.maximum(
                b_lc_mps2, np.minimum(np.abs(np.nan_to_num(tf.dv_long_mps)), cfg.b_max_mps2)
            ),
            b_lc_mps2,
        )
    b_lc_mps2 = np.where(cancel_front, 0.0, b_lc_mps2)
    still_lc = is_lc & ~cancel_front
    has_rear = still_lc & tr.valid
    rear_gap_m = -tr.d_long_m  # bumper gap to the rear vehicle (< 0: overlapping)
    rear_margin_m = 0.0
    if stopping:  # the rear vehicle must be able to brake for the CAV (a CAV rear reacts late)
        rear = np.maximum(pairs[..., 1], 0)
        rear_speed_mps = take(state.speed_mps, rear) * np.abs(np.cos(take(state.heading_rad, rear)))
        # A rear CAV reacts after a step and may accelerate during it.
        rear_cav = take(state.is_cav, rear)
        reaction_s = np.where(rear_cav, step_s, 0.0)
        rear_end_mps = rear_speed_mps + np.where(rear_cav, dv_action, 0.0)
        rear_margin_m = safe_gap_m(
            rear_speed_mps, ego_speed_mps, reaction_s, safe_decel, rear_end_mps
        )
    cancel_rear = has_rear & (
        (rear_gap_m <= cfg.d_lc_min_m + rear_margin_m)
        | tr.risk(cfg.d_safe_m, cfg.ttc_safe_s)
        | (
            (tr.risk(cfg.d_safe_m, cfg.ttc_att_s) | tr.risk(cfg.d_att_m, cfg.ttc_safe_s))
            & (b_lc_mps2 != 0.0)
        )
    )
    cancel = cancel_front | cancel_rear
    # CAVs are connected: of two CAVs changing into the same lane, or towards each
    # other into adjacent lanes, side by side (neither sees the other as a target-lane
    # neighbour yet), only the front one goes.
    moving = still_lc & ~cancel_rear
    target_lane = lane + offset  # (..., C)
    i_, j_ = (Ellipsis, slice(None), None), (Ellipsis, None, slice(None))  # [..., i, j] axes
    cav_x_m, cav_length_m = take(state.x_m, cav_index), take(state.length_m, cav_index)
    dx_m = cav_x_m[j_] - cav_x_m[i_]  # (..., C, C) x_j - x_i
    half_lengths_m = 0.5 * (cav_length_m[i_] + cav_length_m[j_])
    pair_gap_m = np.abs(dx_m) - half_lengths_m
    speed_j = np.broadcast_to(ego_speed_mps[j_], dx_m.shape)
    need_m = cfg.d_safe_m + (
        safe_gap_m(ego_speed_mps[i_], speed_j, step_s, safe_decel) if stopping else 0.0
    )
    lanes_apart_after = np.abs(target_lane[i_] - target_lane[j_])  # (..., C, C)
    lanes_apart_now = np.abs(lane[i_] - lane[j_])
    converging = (lanes_apart_after == 0) | (
        (lanes_apart_after == 1) & (lanes_apart_now > lanes_apart_after)
    )
    rows = np.arange(shape[-1])
    j_first = (dx_m > 0) | ((dx_m == 0) & (rows[None, :] < rows[:, None]))  # j ahead of i
    clash = (moving[i_] & moving[j_] & converging & j_first & (pair_gap_m <= need_m)).any(
        axis=-1
    )  # (..., C) i yields to a CAV ahead entering the same lane
    # Nor does a CAV change next to an HDV alongside beyond the target lane: that
    # one may move into the same lane in the same instant, and its intent is unknown.
    dx_all_m = state.x_m[..., None, :] - cav_x_m[..., None]  # (..., C, V)
    half_all_m = 0.5 * (state.length_m[..., None, :] + cav_length_m[..., None])
    beyond = (
        (state.active & ~state.is_cav)[..., None, :]  # a CAV's intent is known (above)
        & (state.lane[..., None, :] == (lane + 2 * offset)[..., None])
        & (np.abs(dx_all_m) - half_all_m <= cfg.d_safe_m)
    ).any(axis=-1)  # (..., C)
    clash |= moving & (offset != 0) & beyond
    cancel |= clash & cfg.coordinate_lane_changes
    a = np.where(cancel, REMAIN, a)
    b_lc_mps2 = np.where(cancel, 0.0, b_lc_mps2)
    mask |= np.where(cancel, RULE_BITS[CANCEL_LC], 0).astype(np.int8)
    mask |= np.where(b_lc_mps2 > 0.0, RULE_BITS[DECEL_LC], 0).astype(np.int8)

    # ---- lines 17-27: car following in the current lane -------------------
    # Evaluated against each front obstacle; the most demanding outcome wins.
    longitudinal = active & ((a == REMAIN) | (a == ACCELERATE) | (a == DECELERATE))
    fires_brake = np.zeros(shape, dtype=bool)  # branch 1 or 3 fired for some obstacle
    fires_suppress = np.zeros(shape, dtype=bool)  # branch 2 or 4 fired for some obstacle
    need_mps = np.zeros(shape)  # "cancel" braking the fired branches ask for
    for sf in own_fronts:
        has_leader = longitudinal & sf.valid
        with np.errstate(invalid="ignore"):
            d_m = np.where(sf.valid, sf.d_long_m, np.inf)
        closing_mps, ttc_s = np.nan_to_num(sf.dv_long_mps), sf.ttc_s  # (..., C)
        extra_m = front_margin_m(sf, a)
        d_warn_m, d_att_m = cfg.d_warn_m + extra_m, cfg.d_att_m + extra_m  # (..., C)
        closing = ttc_s < np.inf  # paper's TTC > 0
        br1 = has_leader & (d_m <= d_warn_m) & closing
        br2 = has_leader & ~br1 & ((d_m <= cfg.d_safe_m) | ((d_m <= d_warn_m) & (a == ACCELERATE)))
        br3 = has_leader & ~br1 & ~br2 & (np.abs(d_m) <= d_att_m) & (ttc_s <= cfg.ttc_warn_s)
        br4 = has_leader & ~br1 & ~br2 & ~br3 & (np.abs(d_m) <= d_att_m)
        br4 &= (ttc_s <= cfg.ttc_att_s) & (a == ACCELERATE)
        need_mps = np.maximum(need_mps, np.where(br1, closing_mps + dv_action, 0.0))
        need_mps = np.maximum(need_mps, np.where(br3, closing_mps, 0.0))
        fires_brake |= br1 | br3
        fires_suppress |= br2 | br4

    speed_change = action_speed_change_mps(a, dv_action) - b_lc_mps2 * step_s  # (..., C)
    if cfg.force_brake == "cancel":
        brake_mps = np.minimum(np.maximum(need_mps, dv_action), max_brake_mps)
        brake = fires_brake & (-brake_mps < speed_change)
    else:  # "paper": Force-Brake = the decelerate action
        brake_mps = np.full(shape, dv_action)
        brake = fires_brake & (a != DECELERATE)
    suppress = fires_suppress & ~fires_brake & (a != REMAIN)
    a = np.where(fires_brake, np.where(brake, DECELERATE, a), np.where(suppress, REMAIN, a))
    speed_change = np.where(brake, -brake_mps, np.where(suppress, 0.0, speed_change))
    mask |= np.where(brake, RULE_BITS[FORCE_BRAKE], 0).astype(np.int8)
    mask |= np.where(suppress, RULE_BITS[SUPPR_ACCEL], 0).astype(np.int8)

    rule = np.full(shape, RULE_NONE, dtype=np.int8)
    for code in (CANCEL_LC, DECEL_LC, FORCE_BRAKE, SUPPR_ACCEL):  # application order
        rule = np.where(mask & RULE_BITS[code], code, rule).astype(np.int8)
    return PSARResult(
        action=np.where(active, a, proposed).astype(np.int64),
        speed_change_mps=np.where(
            active, speed_change, action_speed_change_mps(proposed, dv_action)
        ).astype(np.float64),
        rule=rule,
        rule_mask=mask,
        decel_lc_mps2=b_lc_mps2.astype(np.float64),
        invalid_lc=invalid_lc,
        active=active,
    )


def _cut_in_front(state: TrafficState, cav_index: np.ndarray, road: Map) -> np.ndarray:
    """(..., C) the nearest vehicle ahead of each CAV that is moving across into its
    lane from a neighbouring one (drift > :data:`CUT_IN_DRIFT_M`), -1 if none.

    Every vehicle is a candidate, not only the nearest one of each neighbouring
    lane: a merging HDV is often a queue's head with others alongside the CAV.
    """
    drift_m = state.y_m - road.lane_center_y_m(state.lane)  # (..., V) + = to the left
    side = state.lane[..., None, :] - take(state.lane, cav_index)[..., None]  # (..., C, V)
    toward = ((side == 1) & (drift_m[..., None, :] < -CUT_IN_DRIFT_M)) | (
        (side == -1) & (drift_m[..., None, :] > CUT_IN_DRIFT_M)
    )
    dx_m = state.x_m[..., None, :] - take(state.x_m, cav_index)[..., None]  # (..., C, V)
    candidate = toward & (dx_m >= 0) & state.active[..., None, :]
    dx_m = np.where(candidate, dx_m, np.inf)
    nearest = np.argmin(dx_m, axis=-1)  # (..., C)
    return np.where(np.isfinite(np.min(dx_m, axis=-1)), nearest, -1)


def rule_counts(rule_mask: np.ndarray) -> np.ndarray:
    """(4,) int64: how many entries of a bitmask array have each rule 1..4 set."""
    rule_mask = np.asarray(rule_mask).astype(np.int64).reshape(-1)
    bits = np.array([RULE_BITS[c] for c in range(1, len(RULE_NAMES))], dtype=np.int64)
    return ((rule_mask[:, None] & bits[None, :]) != 0).sum(axis=0).astype(np.int64)
