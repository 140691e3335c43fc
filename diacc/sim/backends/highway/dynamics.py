"""The highway backend's longitudinal dynamics: one integration sub-step and its caches.

:func:`substep` moves every vehicle of every env: IDM (or the CAV's constant
command acceleration), lateral motion of lane changes, collisions and
arrivals. The ``refresh_*`` functions keep :class:`~.simstate.HighwayCaches`
up to date; each docstring says on which events.
"""

from __future__ import annotations

import numpy as np

from diacc.sim.backends.highway.models import box_contacts
from diacc.sim.backends.highway.simstate import HighwaySim
from diacc.sim.state import flat_offsets, take, take_last


def rows_where(mask: np.ndarray, new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """``new`` in the envs of the (E,) ``mask``, ``old`` elsewhere (any trailing shape)."""
    return np.where(mask.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)


def refresh_road_facts(hw: HighwaySim, envs: np.ndarray) -> None:
    """Per-vehicle desired speed and end of the destination lane, in the (E,) ``envs``.

    Refreshed at every decision and lane-change start rather than every
    sub-step: both only change at segment boundaries, so a new speed
    limit takes effect at the next decision (<= ``decision_period_s``).
    """
    state, caches = hw.state, hw.caches
    seg = hw.tables.segment_of(hw.state.x_m)
    desired = hw.tables.speed_limit_mps[seg]
    # Lane end as a centre position: the obstacle's rear is at the end itself.
    end_x = hw.tables.end_m[seg, state.lane_to] + 0.5 * hw.sim.vehicle_length_m
    caches.desired_mps = rows_where(envs, desired, caches.desired_mps)
    caches.end_x_m = rows_where(envs, end_x, caches.end_x_m)
    caches.inv_desired_s_per_m = 1.0 / np.maximum(caches.desired_mps, 1e-3)


def refresh_speed_bounds(hw: HighwaySim) -> None:
    """Per-vehicle speed window of a sub-step: [0, inf) for HDVs, up to / down to
    the commanded target for CAVs, frozen for wrecked and arrived vehicles.

    Idempotent between commands (a frozen vehicle keeps its speed), so
    refreshing every env when one needs it changes nothing for the others.
    """
    state, caches = hw.state, hw.caches
    driving = state.active & ~state.crashed
    up = state.cav_accel_mps2 >= 0.0
    lo = np.where(state.is_cav & ~up, state.cav_target_mps, 0.0)
    hi = np.where(state.is_cav & up, state.cav_target_mps, np.inf)
    caches.v_lo_mps = np.where(driving, lo, state.speed_mps)
    caches.v_hi_mps = np.where(driving, hi, state.speed_mps)
    caches.half_dt_active_s = np.where(state.active, 0.5 * hw.dt_s, 0.0)


def idm_fast(hw: HighwaySim, v: np.ndarray, gap_m: np.ndarray, lead_v: np.ndarray) -> np.ndarray:
    """:func:`idm_accel` with per-vehicle constants folded in (the sub-step hot path)."""
    params, caches = hw.params, hw.caches
    p = params.idm
    free = np.power(v * caches.inv_desired_s_per_m, p.delta)
    dynamic = v * (p.headway_s + (v - lead_v) * params.inv_2_sqrt_ab_s2_per_m)
    s_star = p.min_gap_m + np.maximum(dynamic, 0.0)
    ratio = s_star / np.maximum(gap_m, 1e-2)
    return p.accel_mps2 * (1.0 - free - ratio * ratio)


def refresh_leaders(hw: HighwaySim) -> None:
    """Leader of every vehicle in the envs marked dirty: nearest active vehicle
    ahead sharing a lane.

    (A merger a vehicle yields to is a second leader, handled in the sub-step.)

    Leaders only change when a lane change starts or ends, a vehicle
    arrives or crashes, or yielding changes (vehicles in a shared lane
    cannot pass each other without a collision), so the (V, V) search runs
    on those events only and sub-steps reuse the result.
    """
    state, caches = hw.state, hw.caches
    rows = np.flatnonzero(caches.leaders_dirty)  # (R,) the envs to search again
    every = len(rows) == hw.n_envs
    pick = (lambda a: a) if every else (lambda a: a[rows])  # noqa: E731
    x, lf, lt = pick(state.x_m), pick(state.lane_from), pick(state.lane_to)  # (R, V)
    active, crashed, is_cav = pick(state.active), pick(state.crashed), pick(state.is_cav)
    a, b = (slice(None), slice(None), None), (slice(None), None, slice(None))
    shares_lane = (
        (lf[a] == lf[b]) | (lf[a] == lt[b]) | (lt[a] == lf[b]) | (lt[a] == lt[b])
    )  # (R, V, V)
    dx = x[b] - x[a]  # (R, V, V) x_j - x_i
    ahead = np.where(shares_lane & (dx > 0.0) & active[b], dx, np.inf)
    leader = ahead.argmin(axis=2)  # (R, V)
    has_leader = np.isfinite(take_last(ahead, leader[..., None])[..., 0])

    def of_leader(values: np.ndarray) -> np.ndarray:  # (R, V) values of each leader
        return take_last(values, leader)

    hdv = active & ~is_cav & ~crashed
    guarded = hdv & has_leader & ~of_leader(is_cav)
    # Pairs that can still start a contact: both on the road, not both wrecked.
    pairs_active = active[a] & active[b] & hw.not_self & ~(crashed[a] & crashed[b])
    moving = active & ~crashed & (lf != lt)
    screen = has_leader & ~(crashed & of_leader(crashed))
    for name, value in (
        ("leader", leader),
        ("has_leader", has_leader),
        ("guarded", guarded),
        ("pairs_active", pairs_active),
        ("moving", moving),
        ("screen", screen),
    ):
        if every:
            setattr(caches, name, value)
        else:
            getattr(caches, name)[rows] = value
    caches.leaders_dirty = np.zeros_like(caches.leaders_dirty)


def substep(hw: HighwaySim) -> np.ndarray:
    """Integrate one sub-step for all vehicles; return the (E, V, V) contact matrix.

    (``np.count_nonzero`` tests a bool array for any True at a third of the cost
    of ``.any()``: this runs ten times per decision step.)
    """
    state, caches = hw.state, hw.caches
    m, sim, dt = hw.model, hw.sim, hw.dt_s
    x, v, length = state.x_m, state.speed_mps, sim.vehicle_length_m
    if np.count_nonzero(caches.leaders_dirty):
        refresh_leaders(hw)
    leader = caches.leader
    leader_flat = leader + flat_offsets(leader.shape[:1], leader.shape[1], 1)  # (E, V)

    def at_leader(values: np.ndarray) -> np.ndarray:  # (E, V) values of each leader
        return np.ascontiguousarray(values).reshape(-1).take(leader_flat)

    # HDV longitudinal: IDM towards the nearer of the leader and the end of the
    # destination lane (a standing obstacle; a leader before it stops for it too).
    gap = np.where(caches.has_leader, at_leader(x) - x, np.inf)  # (E, V)
    to_end = caches.end_x_m - x
    end_closer = to_end < gap
    gap = np.where(end_closer, to_end, gap) - length
    lead_v = np.where(end_closer, 0.0, at_leader(v))
    acc = idm_fast(hw, v, gap, lead_v)
    # A yielding follower brakes for the merger *and* for its own leader, whichever
    # asks more: the merger may be alongside the real leader, not in front of it.
    yielding = state.yield_to >= 0
    if np.count_nonzero(yielding):
        merger = np.where(yielding, state.yield_to, hw.own_index)
        acc_merge = idm_fast(hw, v, take(x, merger) - x - length, take(v, merger))
        acc = np.where(yielding, np.minimum(acc, acc_merge), acc)
    # CAVs: constant acceleration towards the commanded target speed.
    acc = np.where(state.is_cav, state.cav_accel_mps2, np.maximum(acc, hw.min_accel_mps2))
    v_new = np.minimum(np.maximum(v + acc * dt, caches.v_lo_mps), caches.v_hi_mps)
    x_new = x + (v + v_new) * caches.half_dt_active_s
    # A CAV cannot drive past the end of its lane: it stops with its front there.
    wall_x = caches.end_x_m - length
    at_wall = state.is_cav & (x_new > wall_x)
    if np.count_nonzero(at_wall):
        hw.stats["cav_lane_end_stops"] += (at_wall & (v_new > 0.0)).sum(axis=1)
        x_new = np.where(at_wall, wall_x, x_new)
        v_new = np.where(at_wall, 0.0, v_new)

    # Last-resort guard: an HDV never runs into the HDV it follows.
    leader_x = at_leader(x_new)
    limit_x = leader_x - length - m.guard_gap_m
    guard = caches.guarded & (x_new > limit_x)
    if np.count_nonzero(guard):
        hw.stats["guard_events"] += guard.sum(axis=1)
        x_new = np.where(guard, limit_x, x_new)
        v_new = np.where(guard, np.minimum(v_new, at_leader(v_new)), v_new)
        leader_x = at_leader(x_new)
    state.x_m, state.speed_mps = x_new, v_new

    # Lateral motion; the manoeuvre completes when the destination centre is reached.
    # Vehicles not changing lanes get lat = 0, y unchanged and heading 0.
    env_moving = caches.moving.any(axis=1)  # (E,)
    any_moving = np.count_nonzero(env_moving) > 0
    if any_moving:
        lat = np.where(caches.moving, state.lat_speed_mps, 0.0)
        y_goal = (state.lane_to + 0.5) * hw.road.lane_width_m
        y_new = state.y_m + lat * dt
        done = caches.moving & ((y_goal - y_new) * np.sign(lat) <= 1e-9)
        state.y_m = np.where(done, y_goal, y_new)
        heading = np.arctan2(lat, v_new)  # v_new >= 0
        state.heading_rad = np.minimum(np.maximum(heading, -m.max_heading_rad), m.max_heading_rad)
        if np.count_nonzero(done):
            state.lane_from = np.where(done, state.lane_to, state.lane_from)
            state.lat_speed_mps = np.where(done, 0.0, state.lat_speed_mps)
            state.cooldown_s = np.where(done, m.lane_change_cooldown_s, state.cooldown_s)
            caches.leaders_dirty |= done.any(axis=1)
    elif caches.heading_nonzero:
        state.heading_rad = np.zeros_like(state.heading_rad)
    caches.heading_nonzero = any_moving
    state.cooldown_s = np.maximum(state.cooldown_s - dt, 0.0)  # LANE_CHANGE_DELAY counts down

    # Collisions: a cheap screen first, the exact box test only if it fires. Without
    # lateral motion every vehicle of an env is straight in one lane and cannot skip
    # over its leader within a sub-step, so only leader pairs can touch; otherwise
    # screen all the env's pairs by bounding boxes.
    maybe = (caches.screen & (leader_x - x_new < length)).any(axis=1)  # (E,)
    if any_moving:  # bounding boxes in the envs with lateral motion (R of them)
        rows = np.flatnonzero(env_moving)
        pick = (lambda a: a) if len(rows) == len(env_moving) else (lambda a: a[rows])  # noqa: E731
        heading, xs, ys = pick(state.heading_rad), pick(x_new), pick(state.y_m)  # (R, V)
        length_m, width_m = sim.vehicle_length_m, sim.vehicle_width_m
        cos_h, sin_h = np.abs(np.cos(heading)), np.abs(np.sin(heading))
        ext_x = 0.5 * (length_m * cos_h + width_m * sin_h)  # (R, V)
        ext_y = 0.5 * (length_m * sin_h + width_m * cos_h)
        near = (np.abs(xs[:, :, None] - xs[:, None, :]) < ext_x[:, :, None] + ext_x[:, None, :]) & (
            np.abs(ys[:, :, None] - ys[:, None, :]) < ext_y[:, :, None] + ext_y[:, None, :]
        )  # (R, V, V)
        maybe[rows] = (near & pick(caches.pairs_active)).any(axis=(1, 2))
    if np.count_nonzero(maybe):
        contact = box_contacts(
            state.x_m,
            state.y_m,
            state.heading_rad,
            length,
            sim.vehicle_width_m,
            state.active,
        )
        contact &= caches.pairs_active & maybe[:, None, None]
        if np.count_nonzero(contact):
            hit = contact.any(axis=1) | contact.any(axis=2)  # (E, V)
            state.crashed |= hit
            state.speed_mps = np.where(hit, 0.0, state.speed_mps)
            state.lat_speed_mps = np.where(hit, 0.0, state.lat_speed_mps)
            refresh_speed_bounds(hw)
            caches.leaders_dirty |= hit.any(axis=1)
    else:
        contact = hw.no_contact

    # Arrivals.
    done_route = state.x_m > state.route_end_m
    if np.count_nonzero(done_route):
        state.active = state.active & ~done_route
        state.arrived |= done_route
        refresh_speed_bounds(hw)
        state.route_end_m = np.where(done_route, np.inf, state.route_end_m)
        caches.leaders_dirty |= done_route.any(axis=1)
    return contact
