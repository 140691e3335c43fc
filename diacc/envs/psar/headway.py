"""Car following of the ``"headway"`` horizon: braking physics in place of lines 17-27.

Every active CAV (lane changers too: they are behind their current leader
during the change) gets the highest safe end-of-step speed
(:func:`~diacc.envs.psar.headway_bound.headway_bound_mps`). A command above it
is lowered: to a smaller acceleration or to ``remain`` (Suppress-Accel,
reported as ``remain``), or, where the CAV must slow down, to braking at up
to the planned deceleration (Force-Brake, reported as ``decelerate``; a lane
change is then cancelled too). How hard a CAV may brake is
``PSARConfig.full_brake`` (:func:`max_brake_mps`).
"""

from __future__ import annotations

import numpy as np

from diacc.config import PSARConfig, SimConfig
from diacc.envs.actions import ACTION_LANE_OFFSET, DECELERATE, REMAIN, action_speed_change_mps
from diacc.envs.psar.headway_bound import end_speed_mps, headway_bound_mps
from diacc.envs.psar.result import (
    CANCEL_LC,
    DECEL_LC,
    FORCE_BRAKE,
    RULE_BITS,
    SUPPR_ACCEL,
    rule_bit,
)
from diacc.envs.psar.scene import Cavs, Obstacles, slot_of
from diacc.sim.kinematics import safe_end_speed_mps
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, stack_last, take


def headway_car_following(
    cavs: Cavs,
    a: np.ndarray,
    b_lc_mps2: np.ndarray,
    mask: np.ndarray,
    near: Obstacles,
    asked_lane: np.ndarray,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Car following of the ``"headway"`` horizon, after the lane-change checks.

    ``asked_lane`` ((..., C), -1: none) is the lane each CAV asked to change
    into: a CAV whose change was cancelled still counts as entering that lane
    for the CAVs behind it there, which then open the gap it needs
    (``cfg.cooperative_merge``; connected CAVs know each other's intent).
    Returns ``(action, speed change, rule mask, b_lc)``.
    """
    state, cav_index, ego_speed_mps = cavs.state, cavs.index, cavs.speed_mps
    slots = slot_of(state, cav_index)  # (..., V)
    brake_mps = max_brake_mps(state, cav_index, slots, near, cfg, sim)  # (..., C)
    offset = ACTION_LANE_OFFSET[a]
    changing = cavs.active & (offset != 0)
    speed_change = action_speed_change_mps(a, sim) - b_lc_mps2 * sim.step_s
    entering_lane = np.where(changing, cavs.lane + offset, asked_lane)  # (..., C) -1: none
    bound_mps, brake_mps = headway_bound_mps(
        cavs, entering_lane, changing, speed_change, slots, near, brake_mps, cfg, road, sim
    )
    end_mps = end_speed_mps(ego_speed_mps, speed_change, bound_mps, brake_mps)
    limited = cavs.active & (end_mps < np.maximum(ego_speed_mps + speed_change, 0.0))
    brake = limited & (end_mps < ego_speed_mps)
    suppress = limited & ~brake
    a = np.where(brake, DECELERATE, np.where(suppress, REMAIN, a))
    b_lc_mps2 = np.where(brake, 0.0, b_lc_mps2)
    speed_change = np.where(limited, end_mps - ego_speed_mps, speed_change)
    mask = mask | rule_bit(brake & changing, CANCEL_LC)
    mask = np.where(brake & changing, mask & ~np.int8(RULE_BITS[DECEL_LC]), mask)
    mask |= rule_bit(brake, FORCE_BRAKE)
    mask |= rule_bit(suppress, SUPPR_ACCEL)
    return a, speed_change, mask.astype(np.int8), b_lc_mps2


def max_brake_mps(
    state: TrafficState,
    cav_index: np.ndarray,
    slots: np.ndarray,
    near: Obstacles,
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
    HDV approached at speed; docs/concepts/psar.md);
    otherwise at most the planned rate, and a gap that a cut-in shortened is
    restored over the next steps. Without it, every cut-in inside the headway
    bound is answered by braking at 5 m/s², an emergency by the metrics'
    threshold (4.5): on SUMO the CAVs' only safety-critical events
    (docs/concepts/psar.md, "When a CAV brakes hard").
    ``"known"``: as ``"threat"``, but a same-lane leader that is a CAV in an
    agent slot is not a threat for being a CAV: its command of this step is
    known, and :func:`~diacc.envs.psar.headway_bound.headway_bound_mps` judges it
    front to back (it brakes harder than planned, is too close, or planned
    braking falls short behind its known motion). Under ``"threat"`` every CAV
    behind a CAV may brake at the full rate whenever its bound asks, which on
    SUMO makes CAV-behind-CAV hard braking the CAVs' remaining safety-critical
    events.

    Args:
        slots: (..., V) each vehicle's agent slot, -1: none
            (:func:`~diacc.envs.psar.scene.slot_of`).
    """
    step_s, planned_mps2 = sim.step_s, sim.cav.safe_decel_mps2
    full_mps, planned_mps = sim.cav.decel_mps2 * step_s, planned_mps2 * step_s
    if cfg.full_brake == "bound":
        return full_mps
    ego_mps = np.maximum(take(state.speed_mps, cav_index), 0.0)[..., None]  # (..., C, 1)
    # The leader and the vehicle merging in ahead, as two columns (..., C, 2).
    index = stack_last([near.sf_index, near.merging_index])
    present = stack_last([near.sf_vehicle.valid, near.merging.valid]) & (index >= 0)
    gap_m = stack_last([near.sf_vehicle.d_long_m, near.merging.d_long_m])
    vehicle = np.maximum(index, 0)
    cav = take(state.is_cav, vehicle)  # (..., C, 2)
    if cfg.full_brake == "known":  # a slotted CAV leader: judged by its command
        cav[..., 0] &= take(slots, vehicle[..., 0]) < 0
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
