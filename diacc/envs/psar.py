"""PSAR, the paper's Algorithm 1: the safety filter between the actor and the simulator.

The actor proposes one action per CAV; :func:`psar` refines it with four
rules (Cancel-LC, Decel-LC, Force-Brake, Suppress-Accel) from the gaps and
TTCs of :mod:`diacc.envs.safety`, and reports which rules took effect
(:class:`PSARResult`), which the metrics and the training logs count
(:func:`rule_counts`). Options and thresholds: :class:`~diacc.config.PSARConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.config import STYLE_PRESETS, PSARConfig, SimConfig
from diacc.envs.actions import (
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
from diacc.envs.safety import (
    SAME_COL,
    PairKinematics,
    SafetyError,
    check_indices,
    lane_end_kinematics,
    lane_leaders_followers,
    pair_kinematics,
)
from diacc.sim.kinematics import braking_step, nan_to_num, safe_end_speed_mps, safe_gap_m
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, flat_offsets, stack_last, take, take_last

#: Rule codes of :attr:`PSARResult.rule`.
RULE_NONE, CANCEL_LC, DECEL_LC, FORCE_BRAKE, SUPPR_ACCEL = 0, 1, 2, 3, 4
RULE_NAMES = ("none", "cancel_lc", "decel_lc", "force_brake", "suppr_accel")
#: Bit of each rule code in :attr:`PSARResult.rule_mask` (``1 << (code - 1)``).
RULE_BITS = {code: 1 << (code - 1) for code in range(1, len(RULE_NAMES))}
#: (4,) int64 the bits of rules 1..4, in order (counting rules over arrays of masks)
RULE_BIT_VALUES = np.array([RULE_BITS[c] for c in range(1, len(RULE_NAMES))], dtype=np.int64)
#: Lateral drift (m) off its lane's centre line towards the ego lane from which a
#: neighbouring-lane vehicle counts as cutting in (both backends keep vehicles on the
#: centre line exactly unless they change lanes).
CUT_IN_DRIFT_M = 0.05


@dataclass(frozen=True)
class _FrontObstacles:
    """What lies ahead of each CAV slot, as the ``"headway"`` car following needs it.

    Found once by the lane-change checks and handed on whole, so the car following
    and its speed bound (:func:`_headway_bound_mps`) read the same obstacles.
    """

    sf_vehicle: PairKinematics  # (..., C) same-lane leader
    sf_index: np.ndarray  # (..., C) its vehicle index (-1: none)
    tf_vehicle: PairKinematics  # (..., C) the target lane's front vehicle (lane changers)
    tf_index: np.ndarray  # (..., C) its vehicle index (-1: none)
    own_wall: PairKinematics  # (..., C) the end of the own lane as a standing obstacle
    merging: PairKinematics  # (..., C) a vehicle ahead moving across into the lane
    merging_index: np.ndarray  # (..., C) its vehicle index (-1: none; :func:`_cut_in_front`)


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
    * Horizon (``cfg.horizon``): ``"stopping"`` (an earlier default)
      lengthens d_warn and d_att, and the lane-change cancel distance d_LC,min to the target-lane
      front and rear vehicles, by Gipps' safe gap
      (:func:`~diacc.sim.kinematics.safe_gap_m`): one decision step of reaction,
      then braking at the CAV's planned deceleration while the vehicle ahead
      brakes as hard (a rear HDV reacts at once, a rear CAV after a step).
      The authors' distances come from a 15 m/s road; at 25 m/s a CAV needs
      about 60 m to brake for a standing queue, and a leader that brakes
      hard needs about one second of headway. ``"paper"`` uses the fixed
      thresholds. Under ``"stopping"`` a moving CAV whose gap is at most the one a
      lane change needs to enter (d_LC,min plus the safe gap at its current speed)
      gets Force-Brake's distance branch (line 19) even when it is not closing:
      else it holds a gap from which it cannot answer a leader that brakes in
      the same step, and closes at one step's braking until it hits.
      ``"headway"`` (issue 26; the default) replaces the car-following block
      (lines 17-27) by braking physics alone (:func:`_headway_car_following`):
      about one second behind an HDV, ``cfg.min_gap_m`` +
      ``cfg.cav_time_gap_s`` behind a CAV whose refined command of this step
      is known (CAVs are refined front to back); the lane-change checks keep
      their structure with these gaps (a rear CAV learns of the change in
      this step, so it needs no reaction step), and CAVs open a gap for a
      CAV that asks to merge in front of them (``cfg.cooperative_merge``);
      a vehicle cutting in (below) is an HDV leader there.
    * Cut-ins: the nearest vehicle ahead in a neighbouring lane whose
      centre has left its lane's centre line towards the ego lane by more
      than :data:`CUT_IN_DRIFT_M` (a lane change into the ego lane under
      way, :func:`_cut_in_front`) is a front obstacle of the car-following
      block too. Without it the CAV sees the merging vehicle only once its
      centre crosses the lane boundary; on SUMO, where an LC2013 driver may
      start a merge from standstill 15-20 m ahead of a CAV (its gap check
      assumes the CAV keeps its speed), the CAV would meanwhile accelerate
      into a gap it can no longer brake for (``bench --safety``: the
      heuristic on train-50 and test-50, ``paper-congestion``, 330 steps).
    * Inactive CAVs keep their proposed action with rule NONE.

    A batch of states ((E, V) arrays, :class:`~diacc.sim.state.TrafficState`) is
    filtered in one call with (E, C) slots and actions; every CAV only ever
    meets vehicles of its own env, and the results are those of E calls.

    Args:
        state: Traffic state the actions will be applied to (or a batch).
        cav_index: (..., C) vehicle indices of the CAV slots.
        proposed_action: (..., C) int actions in 0..4.
        cfg: PSAR thresholds and options.
        road: the :class:`~diacc.sim.maps.Map`.
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
    headway = cfg.horizon == "headway"
    stopping = cfg.horizon == "stopping" or headway  # both size gaps by braking physics
    active = take(state.active, cav_index)  # (..., C)
    proposed = action.astype(np.int64)
    a = proposed.copy()
    mask = np.zeros(shape, dtype=np.int8)
    neighbours = lane_leaders_followers(state, cav_index, check=False)  # (..., C, 3)

    ego_speed_mps = take(state.speed_mps, cav_index) * np.abs(
        np.cos(take(state.heading_rad, cav_index))
    )

    def front_margin_m(
        kin: PairKinematics, action: np.ndarray, front_is_cav: np.ndarray | None = None
    ) -> np.ndarray:
        """Extra distance of the "stopping" horizon behind a front obstacle, 0 for "paper".

        Gipps' safe gap, with the speed the CAV reaches by the end of the step if
        it accelerates as proposed (braking proposals are judged at the current speed).
        """
        if not stopping:
            return np.zeros(shape)
        lead_speed_mps = ego_speed_mps - nan_to_num(kin.dv_long_mps)  # 0 for a wall
        end_speed_mps = ego_speed_mps + np.maximum(action_speed_change_mps(action, dv_action), 0)
        gap_m = safe_gap_m(ego_speed_mps, lead_speed_mps, step_s, safe_decel, end_speed_mps)
        if headway:  # the standstill gap car following will keep
            gap_m = gap_m + max(cfg.min_gap_m - cfg.d_lc_min_m, 0.0)
            if front_is_cav is not None:  # a CAV's command will be known: the platoon gap
                platoon_m = cfg.cav_time_gap_s * ego_speed_mps + cfg.min_gap_m - cfg.d_lc_min_m
                gap_m = np.where(front_is_cav, np.maximum(platoon_m, 0.0), gap_m)
        return np.where(kin.valid, gap_m, 0.0)

    # ---- lane change the road does not allow -> remain ---------------------
    is_lc = active & ((a == LANE_LEFT) | (a == LANE_RIGHT))
    invalid_lc = is_lc & ~lane_change_allowed(state, cav_index, a, road, sim)
    a = np.where(invalid_lc, REMAIN, a)
    is_lc &= ~invalid_lc
    asked_lane = np.where(is_lc, take(state.lane, cav_index) + ACTION_LANE_OFFSET[a], -1)
    offset = ACTION_LANE_OFFSET[a]  # (..., C)
    lane = take(state.lane, cav_index).astype(np.int64)

    # ---- lines 2-16: lane-change checks on the target lane ----------------
    col = (offset + 1)[..., None]  # (..., C, 1) column of the target lane in LaneNeighbours
    pairs = stack_last(
        [
            take_last(neighbours.front, col)[..., 0],
            take_last(neighbours.rear, col)[..., 0],
            neighbours.front[..., SAME_COL],
        ],
    )  # (..., C, 3): target-lane front j, target-lane rear k, same-lane front j
    cut_in = _cut_in_front(state, cav_index, road)  # (..., C)
    # One call per kind of obstacle (the formulas are elementwise): the three neighbours
    # and the vehicle cutting in as columns, the target and own lanes' ends side by side.
    others = np.concatenate([pairs, cut_in[..., None]], -1)  # (..., C, 4)
    # checked slots, found neighbours; the ego column broadcasts against the four others
    kin = pair_kinematics(state, cav_index[..., None], others, check=False)
    tf_vehicle, tr, sf_vehicle, cut_in_vehicle = (kin.column(k) for k in range(4))
    n_cav = shape[-1]
    walls = lane_end_kinematics(
        state,
        np.concatenate([cav_index, cav_index], -1),
        np.concatenate([lane + offset, lane], -1),
        road,
        cfg.queue_gap_m,
    )  # (..., 2C)
    # Front obstacles: the leader, and the end of the lane (with its queue) as a wall.
    target_fronts = [tf_vehicle, walls.column(slice(None, n_cav))]
    own_fronts = [sf_vehicle, walls.column(slice(n_cav, None)), cut_in_vehicle]

    cancel_front = np.zeros(shape, dtype=bool)
    b_lc_mps2 = np.zeros(shape)
    # Under "headway" a CAV in front is followed with its command known (car following).
    tf_cav = take(state.is_cav, np.maximum(pairs[..., 0], 0)) & tf_vehicle.valid
    for tf, tf_is_cav in zip(target_fronts, (tf_cav, None), strict=True):
        has_front = is_lc & tf.valid
        cancel = has_front & (
            (tf.d_long_m <= cfg.d_lc_min_m + front_margin_m(tf, a, tf_is_cav))
            | tf.risk(cfg.d_safe_m, cfg.ttc_safe_s)
        )
        decel = has_front & (
            tf.risk(cfg.d_safe_m, cfg.ttc_att_s) | tf.risk(cfg.d_att_m, cfg.ttc_safe_s)
        )
        cancel_front |= cancel
        b_lc_mps2 = np.where(
            decel,
            np.maximum(b_lc_mps2, np.minimum(np.abs(nan_to_num(tf.dv_long_mps)), cfg.b_max_mps2)),
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
        rear_cav = take(state.is_cav, rear)
        if headway:
            # A rear CAV learns of the change in this step (it is refined after the
            # changer) and can brake for it at once; it then restores its full gap.
            reaction_s, rear_end_mps = 0.0, rear_speed_mps
            extra_m = np.where(rear_cav, cfg.cav_time_gap_s * rear_speed_mps, 0.0)
        else:  # a rear CAV reacts after a step and may accelerate during it
            reaction_s = np.where(rear_cav, step_s, 0.0)
            rear_end_mps = rear_speed_mps + np.where(rear_cav, dv_action, 0.0)
            extra_m = 0.0
        rear_margin_m = extra_m + safe_gap_m(
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

    if headway:
        a, speed_change, mask, b_lc_mps2 = _headway_car_following(
            state,
            cav_index,
            a,
            b_lc_mps2,
            mask,
            _FrontObstacles(
                sf_vehicle=sf_vehicle,
                sf_index=pairs[..., 2],
                tf_vehicle=tf_vehicle,
                tf_index=pairs[..., 0],
                own_wall=own_fronts[1],
                merging=own_fronts[2],
                merging_index=cut_in,
            ),
            ego_speed_mps,
            asked_lane if cfg.cooperative_merge else np.full(shape, -1),
            cfg,
            road,
            sim,
        )
        return _result(a, proposed, speed_change, mask, b_lc_mps2, invalid_lc, active, dv_action)

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
        closing_mps, ttc_s = nan_to_num(sf.dv_long_mps), sf.ttc_s  # (..., C)
        extra_m = front_margin_m(sf, a)
        d_warn_m, d_att_m = cfg.d_warn_m + extra_m, cfg.d_att_m + extra_m  # (..., C)
        closing = ttc_s < np.inf  # paper's TTC > 0
        # "stopping": a gap shorter than the one a lane change needs to enter
        # (d_LC,min + Gipps) is closed in effect, even at equal speeds: the leader
        # may brake in this very step, and a CAV that answers a step late keeps
        # closing at that step's braking until it hits (bench --safety, test-50).
        # Judged at the CAV's current speed (as for ``remain``), whatever it proposed.
        hold_m = cfg.d_lc_min_m + front_margin_m(sf, np.full(shape, REMAIN))
        too_short = stopping & (ego_speed_mps > 0.0) & (d_m <= hold_m)
        br1 = has_leader & (d_m <= d_warn_m) & (closing | too_short)
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

    return _result(a, proposed, speed_change, mask, b_lc_mps2, invalid_lc, active, dv_action)


def _result(
    a: np.ndarray,
    proposed: np.ndarray,
    speed_change: np.ndarray,
    mask: np.ndarray,
    b_lc_mps2: np.ndarray,
    invalid_lc: np.ndarray,
    active: np.ndarray,
    dv_action: float,
) -> PSARResult:
    """The :class:`PSARResult` of refined actions; inactive CAVs keep their proposal."""
    rule = np.full(a.shape, RULE_NONE, dtype=np.int8)
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
    return ((rule_mask[:, None] & RULE_BIT_VALUES) != 0).sum(axis=0).astype(np.int64)


def _headway_car_following(
    state: TrafficState,
    cav_index: np.ndarray,
    a: np.ndarray,
    b_lc_mps2: np.ndarray,
    mask: np.ndarray,
    fronts: _FrontObstacles,
    ego_speed_mps: np.ndarray,
    asked_lane: np.ndarray,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Car following of the ``"headway"`` horizon, after the lane-change checks.

    Every active CAV (lane changers too: they are behind their current leader
    during the change) gets the highest safe end-of-step speed
    (:func:`_headway_bound_mps`). A command above it is lowered: to a smaller
    acceleration or to ``remain`` (Suppress-Accel, reported as ``remain``),
    or, where the CAV must slow down, to braking at up to the planned
    deceleration (Force-Brake, reported as ``decelerate``; a lane change is
    then cancelled too). ``asked_lane`` ((..., C), -1: none) is the lane each
    CAV asked to change into: a CAV whose change was cancelled still counts
    as entering that lane for the CAVs behind it there, which then open the
    gap it needs (``cfg.cooperative_merge``; connected CAVs know each
    other's intent). Returns ``(action, speed change, rule mask, b_lc)``.
    """
    step_s, dv_action = sim.step_s, sim.speed_change_mps
    slot_of = _slot_of(state, cav_index)  # (..., V)
    max_brake_mps = _max_brake_mps(state, cav_index, slot_of, fronts, cfg, sim)  # (..., C)
    active = take(state.active, cav_index)
    offset = ACTION_LANE_OFFSET[a]
    changing = active & (offset != 0)
    speed_change = action_speed_change_mps(a, dv_action) - b_lc_mps2 * step_s  # (..., C)
    lane = take(state.lane, cav_index).astype(np.int64)
    entering_lane = np.where(changing, lane + offset, asked_lane)  # (..., C) -1: none
    bound_mps, max_brake_mps = _headway_bound_mps(
        state,
        cav_index,
        entering_lane,
        changing,
        speed_change,
        slot_of,
        fronts,
        max_brake_mps,
        cfg,
        road,
        sim,
    )
    end_mps = _end_speed_mps(ego_speed_mps, speed_change, bound_mps, max_brake_mps)
    limited = active & (end_mps < np.maximum(ego_speed_mps + speed_change, 0.0))
    brake = limited & (end_mps < ego_speed_mps)
    suppress = limited & ~brake
    a = np.where(brake, DECELERATE, np.where(suppress, REMAIN, a))
    b_lc_mps2 = np.where(brake, 0.0, b_lc_mps2)
    speed_change = np.where(limited, end_mps - ego_speed_mps, speed_change)
    mask = mask | np.where(brake & changing, RULE_BITS[CANCEL_LC], 0).astype(np.int8)
    mask = np.where(brake & changing, mask & ~np.int8(RULE_BITS[DECEL_LC]), mask)
    mask |= np.where(brake, RULE_BITS[FORCE_BRAKE], 0).astype(np.int8)
    mask |= np.where(suppress, RULE_BITS[SUPPR_ACCEL], 0).astype(np.int8)
    return a, speed_change, mask.astype(np.int8), b_lc_mps2


def _max_brake_mps(
    state: TrafficState,
    cav_index: np.ndarray,
    slot_of: np.ndarray,
    fronts: _FrontObstacles,
    cfg: PSARConfig,
    sim: SimConfig,
) -> np.ndarray | float:
    """(..., C) the largest speed drop a CAV may command in this step (``cfg.full_brake``).

    ``"bound"``: the physical limit whenever the speed bound asks for it.
    ``"threat"``: the physical limit only under a threat, i.e. when the leader
    or a vehicle merging in ahead brakes harder than the planned rate (it did
    in the last step), is a CAV (whose own command may be a full brake), is
    closer than ``cfg.min_gap_m``, or is so much slower that braking at the
    planned rate would not keep ``cfg.min_gap_m`` even if it only went on as
    it does now (its current deceleration, then the planned rate: a standing
    HDV approached at speed; learning evidence, train-50 seed 2001644268);
    otherwise at most the planned rate, and a gap that a cut-in shortened is
    restored over the next steps. Without it, every cut-in inside the headway
    bound is answered by braking at 5 m/s², an emergency by the metrics'
    threshold (4.5): on SUMO the CAVs' only safety-critical events (train-50,
    ``realistic``, shipped agent).
    ``"known"``: as ``"threat"``, but a same-lane leader that is a CAV in an
    agent slot is not a threat for being a CAV: its command of this step is
    known, and :func:`_headway_bound_mps` judges it front to back (it brakes
    harder than planned, is too close, or planned braking falls short behind
    its known motion). Under ``"threat"`` every CAV behind a CAV may brake at
    the full rate whenever its bound asks, which on SUMO makes CAV-behind-CAV
    hard braking the CAVs' remaining safety-critical events.
    """
    step_s, planned_mps2 = sim.step_s, sim.cav.safe_decel_mps2
    full_mps, planned_mps = sim.cav.decel_mps2 * step_s, planned_mps2 * step_s
    if cfg.full_brake == "bound":
        return full_mps
    ego_mps = np.maximum(take(state.speed_mps, cav_index), 0.0)[..., None]  # (..., C, 1)
    # The leader and the vehicle merging in ahead, as two columns (..., C, 2).
    index = stack_last([fronts.sf_index, fronts.merging_index])
    present = stack_last([fronts.sf_vehicle.valid, fronts.merging.valid]) & (index >= 0)
    gap_m = stack_last([fronts.sf_vehicle.d_long_m, fronts.merging.d_long_m])
    vehicle = np.maximum(index, 0)
    cav = take(state.is_cav, vehicle)  # (..., C, 2)
    if cfg.full_brake == "known":  # a slotted CAV leader: judged by its command
        cav[..., 0] &= take(slot_of, vehicle[..., 0]) < 0
    accel_mps2 = take(state.accel_mps2, vehicle)
    braking = accel_mps2 < -planned_mps2
    # The vehicle ahead goes on as now (braking no harder than planned), then brakes
    # at the planned rate; the CAV brakes at the planned rate from this step on.
    lead_mps = np.maximum(take(state.speed_mps, vehicle), 0.0)
    lead_end_mps = np.maximum(lead_mps + np.minimum(accel_mps2, 0.0) * step_s, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        lead_step_m = np.where(
            lead_mps + accel_mps2 * step_s > 0.0,
            0.5 * (lead_mps + lead_end_mps) * step_s,
            lead_mps**2 / (2.0 * np.maximum(-accel_mps2, 1e-9)),  # stops within the step
        )
        close = gap_m < cfg.min_gap_m
        planned_end_mps = safe_end_speed_mps(
            gap_m, ego_mps, lead_step_m, lead_end_mps, step_s, planned_mps2, cfg.min_gap_m
        )
        falls_short = planned_end_mps < ego_mps - planned_mps
    threat = (present & (braking | cav | close | falls_short)).any(-1)  # (..., C)
    return np.where(threat, full_mps, planned_mps)


def _slot_of(state: TrafficState, cav_index: np.ndarray) -> np.ndarray:
    """(..., V) the agent slot of each vehicle (-1: an HDV, or a CAV without a slot)."""
    slot_of = np.full(state.x_m.shape, -1, np.int64)
    flat = cav_index + flat_offsets(cav_index.shape[:-1], state.n_vehicles, 1)  # into (E * V,)
    # Repeated vehicles (empty slots): the last slot wins.
    slot_of.reshape(-1)[flat] = np.broadcast_to(np.arange(cav_index.shape[-1]), flat.shape)
    return slot_of


def _end_speed_mps(
    speed_mps: np.ndarray,
    proposed_mps: np.ndarray,
    bound_mps: np.ndarray,
    max_brake_mps: np.ndarray | float,
) -> np.ndarray:
    """End-of-step speed a CAV commands: its proposal, or the bound (braking <= ``max_brake``)."""
    proposed_end = np.maximum(speed_mps + proposed_mps, 0.0)
    limited = np.maximum(np.maximum(bound_mps, speed_mps - max_brake_mps), 0.0)
    return np.where(proposed_end <= np.maximum(bound_mps, 0.0), proposed_end, limited)


def _exit_room_m(state: TrafficState, cav_index: np.ndarray, road: Map) -> np.ndarray:
    """(..., C) how far before its lane's end a CAV must stop to still be able to leave.

    A lane whose neighbours end no later (the outer lane of a two-lane drop)
    can only be left into a lane that ends as soon, and a change needs the
    target lane to last the vehicle's length beyond its centre even from
    standstill (:meth:`Map.lane_change_allowed`): stopping at the very end
    would trap the CAV. So its wall moves back to where the change is still
    allowed, plus half a metre. 0 where a neighbour outlasts the lane.
    """
    seg = take(state.segment, cav_index).astype(np.int64)
    lane = take(state.lane, cav_index).astype(np.int64)
    own_ends_m, exit_ends_m = road.exit_ends_m()  # (S, L) each
    own_end_m, exit_end_m = own_ends_m[seg, lane], exit_ends_m[seg, lane]  # (..., C)
    length_m = take(state.length_m, cav_index)
    trapped = np.isfinite(own_end_m) & np.isfinite(exit_end_m) & (exit_end_m <= own_end_m)
    with np.errstate(invalid="ignore"):  # inf - inf where no lane ends
        room_m = own_end_m - (exit_end_m - 0.5 * length_m - 0.5)  # front stays behind this
    return np.where(trapped, np.maximum(room_m, 0.0), 0.0)


def _headway_bound_mps(
    state: TrafficState,
    cav_index: np.ndarray,
    entering_lane: np.ndarray,
    changing: np.ndarray,
    speed_change_mps: np.ndarray,
    slot_of: np.ndarray,
    fronts: _FrontObstacles,
    max_brake_mps: np.ndarray | float,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig,
) -> tuple[np.ndarray, np.ndarray | float]:
    """(..., C) highest safe end-of-step speed per CAV under the ``"headway"`` horizon,
    and the speed drop each CAV may command (``max_brake_mps``, refined under
    ``full_brake = "known"`` once the CAVs it follows are decided).

    Every front obstacle gives a bound (:func:`~diacc.sim.kinematics.safe_end_speed_mps`):
    the same-lane leader, the end of the own lane (not for a CAV leaving it:
    the road checked the change's reach) and each CAV ahead that changes,
    or asks to change, into the lane in this step (each one, not only the
    nearest: a nearer one that only asks may drive on and uncover one that
    moves in standing; learning evidence, train-50 seed 1637607931). An HDV leader,
    whose command is unknown, may brake at once as hard as its style's
    deceleration (at least the planned rate ``sim.cav.safe_decel_mps2``),
    and the CAV plans to answer with its full braking ``sim.cav.decel_mps2``:
    about one second of headway (Gipps with one step of reaction). A CAV leader's
    command of this step is known, so CAVs are refined front to back: a CAV is
    bounded once every CAV it follows is decided, and then needs only
    ``cfg.min_gap_m`` plus ``cfg.cav_time_gap_s`` of its speed, because from
    the next step on it learns of the leader's braking in the step the leader
    brakes. (A dependency cycle, possible only between CAVs exactly
    alongside, keeps the unknown-leader bound.)

    Args:
        entering_lane: (..., C) lane each CAV changes or asks to change into (-1: none).
        changing: (..., C) bool, the CAV changes lanes in this step.
        speed_change_mps: (..., C) commands before car following.
        slot_of: (..., V) each vehicle's agent slot, -1: none (:func:`_slot_of`).
        fronts: what lies ahead (:class:`_FrontObstacles`); the merging vehicle
            is followed like an HDV leader.
        max_brake_mps: (..., C) the speed drop each CAV may command (:func:`_max_brake_mps`).
    """
    step_s, decel = sim.step_s, sim.cav.safe_decel_mps2
    full_mps, planned_mps = sim.cav.decel_mps2 * step_s, decel * step_s
    limit_mps = road.speed_limits_mps()

    def long_speed(vehicles: np.ndarray) -> np.ndarray:
        return take(state.speed_mps, vehicles) * np.abs(np.cos(take(state.heading_rad, vehicles)))

    ego_mps = long_speed(cav_index)  # (..., C)

    def bound(
        gap_m, lead_step_m, lead_end_mps, time_gap_s, own_decel=decel, lead_decel=None, own=None
    ):
        with np.errstate(invalid="ignore"):
            out = safe_end_speed_mps(
                gap_m,
                ego_mps if own is None else own,
                lead_step_m,
                lead_end_mps,
                step_s,
                own_decel,
                cfg.min_gap_m,
                time_gap_s,
                lead_decel,
            )
        return np.where(np.isfinite(gap_m), out, np.inf)

    lead = np.maximum(fronts.sf_index, 0)
    lead_slot = np.where(fronts.sf_vehicle.valid, take(slot_of, lead), -1)  # (..., C)
    lead_gap_m = np.where(fronts.sf_vehicle.valid, fronts.sf_vehicle.d_long_m, np.inf)
    # An HDV leader may brake as hard as its style does, at least at the CAVs' planned
    # rate; behind one the CAV is ready to use its full braking (an emergency).
    style_decel_mps2 = np.array([st.decel_mps2 for st in STYLE_PRESETS[sim.style_preset]])

    def behind_hdv(gap_m: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
        """(..., C, K) bound behind HDVs ``vehicle`` (..., C, K) at ``gap_m``."""
        style = np.maximum(take(state.style, vehicle).astype(np.int64), 0)  # CAV: strictest
        hdv_decel_mps2 = np.maximum(style_decel_mps2[style], decel)  # (..., C)
        step_m, end_mps = braking_step(long_speed(vehicle), step_s, hdv_decel_mps2)
        return bound(
            gap_m, step_m, end_mps, 0.0, sim.cav.decel_mps2, hdv_decel_mps2, ego_mps[..., None]
        )

    merging_gap_m = np.where(fronts.merging.valid, fronts.merging.d_long_m, np.inf)
    # The leader and the vehicle merging in, as two columns of one call (elementwise).
    hdv_lead_mps, merging_mps = np.moveaxis(
        behind_hdv(
            stack_last([lead_gap_m, merging_gap_m]),
            stack_last([lead, np.maximum(fronts.merging_index, 0)]),
        ),
        -1,
        0,
    )  # (..., C) each
    wall_gap_m = np.where(fronts.own_wall.valid & ~changing, fronts.own_wall.d_long_m, np.inf)
    wall_gap_m = wall_gap_m - _exit_room_m(state, cav_index, road)
    fixed_mps = np.minimum(
        bound(wall_gap_m, 0.0, 0.0, 0.0), np.where(lead_slot >= 0, np.inf, hdv_lead_mps)
    )
    fixed_mps = np.minimum(fixed_mps, merging_mps)

    # Every CAV ahead changing into each CAV's lane: (..., C, C) [i, j] = j cuts in. Each
    # one bounds, not only the nearest: a nearer one that only asks (and drives on in its
    # own lane) does not shield the CAV from one that moves in, standing, further ahead.
    i_, j_ = (Ellipsis, slice(None), None), (Ellipsis, None, slice(None))
    cav_x_m, cav_length_m = take(state.x_m, cav_index), take(state.length_m, cav_index)
    lane = take(state.lane, cav_index).astype(np.int64)
    dx_m = cav_x_m[j_] - cav_x_m[i_]
    pair_gap_m = dx_m - 0.5 * (cav_length_m[i_] + cav_length_m[j_])
    # One asking but not changing is yielded to only from far enough behind for it to
    # pass the rear check (gap > d_LC,min once the yielding CAV stands); a CAV closer or
    # alongside drives on and lets it in behind. So of a CAV standing at a lane end and
    # a standing CAV behind it in the target lane one always moves (the zipper's
    # liveness, docs/concepts/psar.md).
    asking = ~changing[j_] & (pair_gap_m <= cfg.d_lc_min_m)
    cuts = (entering_lane[j_] == lane[i_]) & (entering_lane[j_] >= 0) & (dx_m > 0) & ~asking
    cut_gap_m = np.where(cuts, pair_gap_m, np.inf)  # (..., C, C)

    # A lane changer also follows the front CAV of its target lane (an HDV there was
    # checked with the unknown-leader gap before the change was allowed).
    tf_slot = np.where(
        changing & fronts.tf_vehicle.valid, take(slot_of, np.maximum(fronts.tf_index, 0)), -1
    )
    tf_gap_m = np.where(tf_slot >= 0, fronts.tf_vehicle.d_long_m, np.inf)
    known = ((lead_slot, lead_gap_m), (tf_slot, tf_gap_m))
    # The CAVs each CAV may follow with their command known, as columns of one (..., C, C + 4)
    # table: every CAV cutting in, then the same-lane leader and the target-lane front CAV
    # (followed: C + 2 columns), then those two again for the threat test of "known" (with
    # their own gap and no time gap). One call of the elementwise formula per pass gives
    # the values of one call per kind of leader, at a fraction of the calls.
    n_cav = cav_index.shape[-1]
    lead_cols = stack_last([np.maximum(slot, 0) for slot, _ in known])  # (..., C, 2)
    known_leads = stack_last([slot >= 0 for slot, _ in known])  # (..., C, 2)
    known_gaps_m = stack_last([gap for _, gap in known])  # (..., C, 2)
    cols = np.concatenate(
        [np.broadcast_to(np.arange(n_cav), cuts.shape), lead_cols, lead_cols], -1
    )  # (..., C, C + 4)
    n_followed = n_cav + 2
    follows = np.concatenate([cuts, known_leads], -1)  # (..., C, C + 2)
    gap_m = np.concatenate(
        [cut_gap_m, np.where(known_leads, known_gaps_m, np.inf), known_gaps_m], -1
    )  # (..., C, C + 4)
    time_gap_s = np.array([cfg.cav_time_gap_s] * n_followed + [0.0, 0.0])  # (C + 4,)
    followed_finite = np.isfinite(gap_m[..., :n_followed])
    # Gathers of (..., C) values by column, through one flat index made once.
    flat_cols = (cols + flat_offsets(cav_index.shape[:-1], n_cav, 2)).reshape(-1)

    def of_cols(values: np.ndarray) -> np.ndarray:
        """(..., C, C + 4): ``values`` (..., C) of the CAVs in each column of ``cols``."""
        return np.ascontiguousarray(values).reshape(-1).take(flat_cols).reshape(cols.shape)

    ahead_v0_mps = of_cols(ego_mps)  # (..., C, C + 4)
    lead_v0_mps = ahead_v0_mps[..., n_followed:]  # (..., C, 2)
    own_mps = ego_mps[..., None]

    def behind(end_mps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """With every CAV ahead ending the step at ``end_mps``: (..., C) bound behind every
        CAV followed (``follows``), and (..., C) whether a known CAV ahead is a threat (it
        brakes harder than planned, is too close, or planned braking falls short)."""
        v1 = of_cols(end_mps)
        with np.errstate(invalid="ignore"):
            out = safe_end_speed_mps(
                gap_m,
                own_mps,
                0.5 * (ahead_v0_mps + v1) * step_s,
                v1,
                step_s,
                decel,
                cfg.min_gap_m,
                time_gap_s,
            )
        followed = np.where(followed_finite, out[..., :n_followed], np.inf)
        planned_end_mps, lead_v1 = out[..., n_followed:], v1[..., n_followed:]
        hard = lead_v0_mps - lead_v1 > planned_mps + 1e-9
        short = planned_end_mps < own_mps - planned_mps
        threat = known_leads & (hard | short | (known_gaps_m < cfg.min_gap_m))
        return followed.min(-1, initial=np.inf), threat.any(-1)

    known_leaders = cfg.full_brake == "known"
    cav_limit_mps = limit_mps[take(state.segment, cav_index).astype(np.int64)]
    brake_mps = np.broadcast_to(np.asarray(max_brake_mps, float), cav_index.shape).copy()
    bound_mps = fixed_mps.copy()
    end_mps = np.zeros(cav_index.shape)  # (..., C) decided end-of-step speed
    decided = ~take(state.active, cav_index)
    for _ in range(n_cav + 1):  # one pass per CAV a chain can hold, at most
        if np.count_nonzero(decided) == decided.size:  # all decided (.all(), cheaper)
            break
        ready = ~decided & ~(follows & ~of_cols(decided)[..., :n_followed]).any(-1)
        if not np.count_nonzero(ready):
            break
        if np.count_nonzero(follows & ready[..., None]):
            followed_mps, threat = behind(end_mps)
        else:  # no CAV decided now follows one (the first pass: CAVs followed are undecided)
            followed_mps, threat = np.inf, False
        now = np.minimum(fixed_mps, followed_mps)
        bound_mps = np.where(ready, now, bound_mps)
        brake_now = brake_mps
        if known_leaders:
            brake_now = np.where(threat, full_mps, brake_now)
            brake_mps = np.where(ready, brake_now, brake_mps)
        # What the backend makes of the command: within the speed limit (lower is safer).
        end_now = np.minimum(
            _end_speed_mps(ego_mps, speed_change_mps, now, brake_now), cav_limit_mps
        )
        end_mps = np.where(ready, end_now, end_mps)
        decided |= ready
    if decided.all():
        return bound_mps, (brake_mps if known_leaders else max_brake_mps)
    # Left undecided (a cycle): the CAVs ahead are treated as HDVs.
    worst_mps = fixed_mps
    for slot, gap_m in known:
        speed_mps = take_last(ego_mps, np.maximum(slot, 0))
        gap_m = np.where(slot >= 0, gap_m, np.inf)
        worst_mps = np.minimum(
            worst_mps, bound(gap_m, *braking_step(speed_mps, step_s, decel), 0.0)
        )
    cut_step_m, cut_end_mps = braking_step(ego_mps[j_], step_s, decel)
    worst_cut_mps = bound(cut_gap_m, cut_step_m, cut_end_mps, 0.0, own=ego_mps[i_])
    worst_mps = np.minimum(worst_mps, worst_cut_mps.min(-1, initial=np.inf))
    bound_mps = np.where(decided, bound_mps, worst_mps)
    if not known_leaders:
        return bound_mps, max_brake_mps
    return bound_mps, np.where(decided, brake_mps, full_mps)
