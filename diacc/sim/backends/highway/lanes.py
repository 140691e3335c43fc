"""Lane changes on the highway backend: CAV commands, MOBIL, forced merges, yielding.

A lane change starts here (:func:`start_changes`) and is then carried out by
the lateral motion of :func:`~.dynamics.substep`. CAVs change lanes when
commanded (:func:`apply_cav_commands`); HDVs and self-driven CAVs decide
every ``decision_period_s`` (:func:`decide_lane_changes`).
"""

from __future__ import annotations

import numpy as np

from diacc.sim.backends.highway.dynamics import (
    refresh_road_facts,
    refresh_speed_bounds,
    rows_where,
)
from diacc.sim.backends.highway.models import idm_accel
from diacc.sim.backends.highway.simstate import HighwaySim
from diacc.sim.kinematics import lane_change_reach_m, safe_gap_m
from diacc.sim.state import take, take_last


def apply_cav_commands(hw: HighwaySim, lane_cmd: np.ndarray, dv_cmd: np.ndarray) -> None:
    """Fix each CAV's acceleration for the step and start commanded lane changes."""
    state = hw.state
    seg = hw.tables.segment_of(hw.state.x_m)
    limit = hw.tables.speed_limit_mps[seg]
    cav = state.is_cav & state.active & ~state.crashed
    target = np.minimum(np.maximum(state.speed_mps + dv_cmd, 0.0), limit)
    accel = np.clip(
        (target - state.speed_mps) / hw.sim.step_s,
        -hw.sim.cav.decel_mps2,
        hw.sim.cav.accel_mps2,
    )
    state.cav_target_mps = np.where(cav, target, state.speed_mps)
    state.cav_accel_mps2 = np.where(cav, accel, 0.0)
    refresh_speed_bounds(hw)

    offset = np.minimum(np.maximum(lane_cmd, -1), 1)
    reach_m = lane_change_reach_m(state.speed_mps, hw.sim.step_s, hw.sim.vehicle_length_m)
    ok = (
        cav
        & (state.lane_from == state.lane_to)
        & hw.road.lane_change_allowed(seg, state.lane_from, offset, state.x_m, reach_m)
    )
    dest_c = np.minimum(np.maximum(state.lane_from + offset, 0), hw.road.max_lanes - 1)
    start_changes(hw, ok, dest_c, hw.sim.step_s)


def start_changes(hw: HighwaySim, start: np.ndarray, dest: np.ndarray, duration_s: float) -> None:
    state, caches = hw.state, hw.caches
    width = hw.road.lane_width_m
    direction = np.sign(dest - state.lane_from)
    state.lane_to = np.where(start, dest, state.lane_to)
    state.lat_speed_mps = np.where(start, direction * width / duration_s, state.lat_speed_mps)
    started = start.any(axis=1)  # (E,)
    if started.any():
        caches.leaders_dirty |= started
        refresh_road_facts(hw, started)
        moving = state.active & ~state.crashed & (state.lane_from != state.lane_to)
        caches.moving = rows_where(started, moving, caches.moving)


def peers(hw: HighwaySim) -> np.ndarray:
    """(E, V, V) bool: j is another vehicle on the road."""
    return hw.not_self & hw.state.active[:, None, :]


def decide_lane_changes(hw: HighwaySim) -> None:
    """MOBIL for HDVs, forced merges for vehicles in ending lanes, yielding followers.

    All vehicles and all three lanes (right, own, left) are evaluated at
    once: one (E, 3, V, V) neighbour search and a single IDM call over every
    acceleration MOBIL needs, stacked as (E, 4, 3, V). An env where no
    vehicle may change lanes gets no change and no yielding from it, as if skipped.
    """
    state, params, caches = hw.state, hw.params, hw.caches
    m, sim, tab = hw.model, hw.sim, hw.tables
    x, v, length = state.x_m, state.speed_mps, sim.vehicle_length_m
    n_envs, n = x.shape
    n_lanes = hw.road.max_lanes
    refresh_road_facts(hw, np.ones(n_envs, dtype=bool))
    seg = hw.tables.segment_of(hw.state.x_m)
    desired = caches.desired_mps

    idle = state.active & ~state.crashed & (state.lane_from == state.lane_to)
    lane = state.lane_from
    dist_end = tab.end_m[seg, lane] - x  # (E, V)
    merge_dir = tab.merge_dir[seg, lane].astype(np.intp)
    # Only HDVs are forced to merge (a CAV that stays in an ending lane stops at its
    # end), and only drivers with a strategic lane-change term (lcStrategic >= 0).
    near_end = idle & (merge_dir != 0) & (dist_end < params.merge_zone_m)
    forced = near_end & params.strategic & ~state.is_cav
    discretionary = (
        idle
        & ~state.is_cav
        & ~near_end
        & (state.cooldown_s <= 0.0)
        & (v >= m.min_lane_change_speed_mps)
    )
    if not (forced.any() or discretionary.any()):
        yielded = (state.yield_to >= 0).any(axis=1)  # (E,)
        if yielded.any():
            state.yield_to[:] = -1
            caches.leaders_dirty |= yielded
        return

    # Neighbours in the right / own / left lane: (E, 3, V) each.
    lanes3 = lane[:, None, :] + hw.sides[None, :, None]  # (E, 3, V)
    lanes3_c = np.minimum(np.maximum(lanes3, 0), n_lanes - 1)
    # [e, side, i, j]: j is on the road in lane ``lanes3[e, side, i]`` (one of the two
    # lanes it occupies while changing lanes), and is not i.
    side_lane = lanes3[..., None]  # (E, 3, V, 1)
    in_lane = (state.lane_from[:, None, None, :] == side_lane) | (
        state.lane_to[:, None, None, :] == side_lane
    )  # (E, 3, V, V)
    in_lane &= peers(hw)[:, None]
    dx = x[:, None, :] - x[:, :, None]  # (E, V, V) x_j - x_i
    ahead = np.where(in_lane & (dx >= 0.0)[:, None], dx[:, None], np.inf)  # (E, 3, V, V)
    behind = np.where(in_lane & (dx < 0.0)[:, None], -dx[:, None], np.inf)
    lead = ahead.argmin(axis=3)  # (E, 3, V)
    foll = behind.argmin(axis=3)
    # The gaps to ``lead`` and ``foll`` (inf: none): the minima, read at the argmins.
    lead_gap = take_last(ahead, lead[..., None])[..., 0] - length
    foll_gap = take_last(behind, foll[..., None])[..., 0] - length
    has_foll = np.isfinite(foll_gap)

    # Every IDM acceleration MOBIL needs, in one call: (E, 4, 3, V) =
    # [ego behind lane leader, ego before lane end, follower behind ego,
    #  follower behind lane leader].
    me = np.broadcast_to(hw.own_index[:, None, :], (n_envs, 3, n))
    ego = np.stack([me, me, foll, foll], axis=1)  # (E, 4, 3, V)
    end_gap = tab.end_m[seg[:, None, :], lanes3_c] - x[:, None, :] - 0.5 * length
    gaps = np.stack([lead_gap, end_gap, foll_gap, foll_gap + lead_gap + length], axis=1)
    lead_v = take(v, lead)  # (E, 3, V)
    v3 = np.broadcast_to(v[:, None, :], (n_envs, 3, n))
    lead_v = np.stack([lead_v, np.zeros_like(lead_v), v3, lead_v], axis=1)
    acc = idm_accel(take(v, ego), take(desired, ego), params.idm.take(ego), gaps, lead_v)
    self_acc = np.minimum(acc[:, 0], acc[:, 1])  # (E, 3, V)
    foll_with_me = np.where(has_foll, acc[:, 2], 0.0)
    foll_without = np.where(has_foll, acc[:, 3], 0.0)

    side = [0, 2]  # rows of the right and left lanes
    dest = lanes3[:, side]  # (E, 2, V)
    dest_c = lanes3_c[:, side]
    seg2 = seg[:, None, :]
    x2 = x[:, None, :]
    valid = (dest >= 0) & (dest < n_lanes) & tab.exists[seg2, dest_c]
    gaps_ok = (lead_gap[:, side] >= m.min_accept_gap_m) & (foll_gap[:, side] >= m.min_accept_gap_m)
    # A CAV follower holds its commanded speed for the rest of the step and only
    # then brakes (at most at its decel limit): the gap must cover that, not IDM.
    foll2 = foll[:, side]  # (E, 2, V)
    cav_foll = take(state.is_cav, foll2) & has_foll[:, side]
    cav_gap_m = sim.cav.min_gap_m + safe_gap_m(
        take(state.cav_target_mps, foll2),
        v[:, None, :],
        sim.step_s,
        sim.cav.safe_decel_mps2,
    )
    gaps_ok &= ~cav_foll | (foll_gap[:, side] >= cav_gap_m)
    nf_after = foll_with_me[:, side]
    gain = (
        self_acc[:, side]
        - self_acc[:, 1:2]
        + params.politeness[:, None, :]
        * (nf_after - foll_without[:, side] + foll_without[:, 1:2] - foll_with_me[:, 1:2])
    )
    mobil_ok = (
        discretionary[:, None, :]
        & valid
        & (tab.end_m[seg2, dest_c] - x2 > m.merge_zone_m + m.merge_lookahead_m)
        & gaps_ok
        & (nf_after >= -m.mobil_max_imposed_brake_mps2)
        & (gain >= params.gain_threshold_mps2[:, None, :])
    )
    # MOBIL's incentive compares the two lanes' IDM accelerations, which are not
    # clipped: with a car cutting in just ahead, a change into a lane behind a much
    # slower car "gains" though it needs more than the driver's physical braking.
    # Like LC2013's secure gap to the new leader, no change the driver cannot brake for.
    own_safe = self_acc[:, side] >= -m.max_brake_mps2  # (E, 2, V)
    hw.stats["unsafe_change_vetoes"] += (mobil_ok & ~own_safe).any(axis=1).sum(axis=1)
    mobil_ok &= own_safe
    urgency = np.minimum(np.maximum(1.0 - dist_end / params.merge_zone_m, 0.0), 1.0)  # (E, V)
    accept_brake = m.mobil_max_imposed_brake_mps2 + urgency * (
        m.forced_max_imposed_brake_mps2 - m.mobil_max_imposed_brake_mps2
    )
    accept_brake2 = accept_brake[:, None, :]
    is_merge = (
        forced[:, None, :] & valid & (merge_dir[:, None, :] == hw.sides[side][None, :, None])
    )  # (E, 2, V)
    forced_ok = (
        is_merge & gaps_ok & (nf_after >= -accept_brake2) & (self_acc[:, side] >= -accept_brake2)
    )
    score = np.where(forced_ok, np.inf, np.where(mobil_ok, gain, -np.inf))  # (E, 2, V)
    start = score.max(axis=1) > -np.inf  # (E, V)
    target = np.where(score.argmax(axis=1) == 0, dest_c[:, 0], dest_c[:, 1])

    # Two vehicles entering the same lane side by side in the same instant
    # would not see each other: keep the front one; of two level ones (two entering
    # the road in the same sub-step, both at its start) the one with the lower index.
    rear_gap_need = params.idm.min_gap_m + v * params.idm.headway_s  # (E, V)
    # (E, V, V) [e, i, j]: j is ahead of i, or level with it and listed before it
    in_front = (dx > 0.0) | ((dx == 0.0) & np.tri(n, k=-1, dtype=bool))
    clash = (
        start[:, :, None]
        & start[:, None, :]
        & (target[:, :, None] == target[:, None, :])
        & hw.not_self
        & (np.abs(dx) - length < np.maximum(rear_gap_need[:, :, None], rear_gap_need[:, None, :]))
        & in_front
    )  # (E, V, V) [e, i, j]: j keeps i out
    start &= ~clash.any(axis=2)

    hw.stats["forced_merges"] += (start & forced).sum(axis=1)
    hw.stats["mobil_changes"] += (start & ~forced).sum(axis=1)
    start_changes(hw, start, target, m.hdv_lane_change_s)

    # Yielding: the nearest follower in the merge lane treats a waiting merger as leader.
    left = merge_dir > 0  # merging into the left lane (row 2), else the right (row 0)
    nf = np.where(left, foll[:, 2], foll[:, 0])  # (E, V)
    nf_gap = np.where(left, foll_gap[:, 2], foll_gap[:, 0])
    nf_acc = np.where(left, foll_with_me[:, 2], foll_with_me[:, 0])
    # (E, V) the follower lets a merger in (zipper preset).
    zipper = take(params.zipper, nf)
    polite = (take(params.politeness, nf) > 0.0) | (v < m.yield_speed_mps) | zipper
    can_brake = np.where(zipper, m.forced_max_imposed_brake_mps2, take(params.idm.decel_mps2, nf))
    waiting = (
        forced
        & ~start
        & (dist_end < m.yield_zone_m)
        & (nf_gap > 0.0)
        & np.isfinite(nf_gap)
        & ~take(state.is_cav, nf)
        & polite
        & (nf_acc >= -can_brake)
    )
    yield_to = np.full_like(state.yield_to, -1)
    for e in np.flatnonzero(waiting.any(axis=1)):  # rare: a merger waits
        mergers = np.flatnonzero(waiting[e])
        order = mergers[np.argsort(-x[e, mergers], kind="stable")]  # nearest written last
        yield_to[e, nf[e, order]] = order
    changed = (yield_to != state.yield_to).any(axis=1)  # (E,)
    state.yield_to = yield_to
    caches.leaders_dirty |= changed
