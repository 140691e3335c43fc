"""Vehicles entering the highway backend: the records of a reset and departures.

A reset turns a drawn population (:func:`diacc.sim.scenario.draw_population`)
into one env's rows of the batch records (:mod:`.simstate`): per-vehicle IDM /
MOBIL parameters of the driver styles, or the CAV vType's. In a ``demand``
scenario vehicles wait *pending* at their slot until they depart
(:func:`insert_due`, the backend's module docstring, "Departure").
"""

from __future__ import annotations

import numpy as np

from diacc.sim.backends.highway.dynamics import refresh_road_facts, refresh_speed_bounds
from diacc.sim.backends.highway.models import IdmParams
from diacc.sim.backends.highway.simstate import HighwayParams, HighwaySim, HighwayState
from diacc.sim.drivers import STYLE_PRESETS
from diacc.sim.scenario import Population


def initial_records(hw: HighwaySim, pop: Population) -> tuple[HighwayParams, HighwayState]:
    """The E = 1 parameter and state records of population ``pop`` at t = 0."""
    n = pop.n_vehicles
    styles = STYLE_PRESETS[hw.sim.style_preset]
    cav = hw.sim.cav
    coop = hw.cav_mode == "cooperative"
    headway_s = hw.cooperative.time_headway_s if coop else cav.time_headway_s
    min_gap_m = hw.cooperative.min_gap_m if coop else cav.min_gap_m
    hdv_style = np.where(pop.is_cav, 0, pop.style).astype(np.intp)

    def per_vehicle(attr: str, cav_value: float) -> np.ndarray:
        table = np.array([getattr(s, attr) for s in styles])
        return np.where(pop.is_cav, cav_value, table[hdv_style])

    def row(value, dtype: type = np.float64) -> np.ndarray:
        """``value`` (a scalar or (V,)) as an E = 1 row of ``dtype``."""
        return np.broadcast_to(np.asarray(value, dtype), (n,))[None].copy()

    idm = IdmParams(
        row(per_vehicle("time_headway_s", headway_s)),
        row(per_vehicle("min_gap_m", min_gap_m)),
        row(per_vehicle("accel_mps2", cav.accel_mps2)),
        row(per_vehicle("decel_mps2", cav.decel_mps2)),
        hw.sim.idm_delta,
    )
    # A late merger (DriverStyle.merge_zone_m) is forced to merge only that close to the end.
    zones = [hw.model.merge_zone_m if s.merge_zone_m is None else s.merge_zone_m for s in styles]
    params = HighwayParams(
        idm=idm,
        inv_2_sqrt_ab_s2_per_m=0.5 / np.sqrt(idm.accel_mps2 * idm.decel_mps2),
        # CAVs that drive themselves (cooperative mode, or no command) change lanes
        # cooperatively; commanded CAVs never run MOBIL.
        politeness=row(per_vehicle("politeness", hw.cooperative.politeness)),
        gain_threshold_mps2=row(
            per_vehicle("lc_gain_threshold_mps2", hw.cooperative.lc_gain_threshold_mps2)
        ),
        # LC2013's lcStrategic < 0 (the authors' cautious drivers): no lane change
        # because a lane ends, so such a driver stops at the end of its lane.
        strategic=row(per_vehicle("lc_strategic", 0.0) >= 0.0, bool),
        zipper=row(per_vehicle("zipper", False), bool),
        merge_zone_m=row(np.where(pop.is_cav, hw.model.merge_zone_m, np.array(zones)[hdv_style])),
        reported_cav=row(pop.is_cav, bool),
        style=row(pop.style, np.int8),
        depart_s=row(pop.depart_s),
    )
    pending = row(pop.depart_s > 0.0, bool)
    speed_mps = row(pop.speed_mps)
    state = HighwayState(
        x_m=row(pop.x_m),
        y_m=row(hw.road.lane_center_y_m(pop.lane)),
        speed_mps=speed_mps,
        lat_speed_mps=row(0.0),
        heading_rad=row(0.0),
        cooldown_s=row(0.0),
        lane_from=row(pop.lane, np.intp),
        lane_to=row(pop.lane, np.intp),
        active=~pending,
        arrived=row(False, bool),
        crashed=row(False, bool),
        pending=pending,
        # Vehicles driven by commands; cooperative CAVs drive like HDVs.
        is_cav=row(False if coop else pop.is_cav, bool),
        yield_to=row(-1, np.intp),
        route_end_m=row(hw.road.length_m),
        cav_target_mps=speed_mps.copy(),
        cav_accel_mps2=row(0.0),
        contact=np.zeros((1, n, n), bool),
        time_s=np.zeros(1),
        step_count=np.zeros(1, np.int64),
    )
    return params, state


def insert_due(hw: HighwaySim, now_s: np.ndarray) -> None:
    """Let pending vehicles whose departure time ``now_s`` (E,) has come enter where
    their lane's entry is free (module docstring, "Departure")."""
    state, params, caches = hw.state, hw.params, hw.caches
    due = state.pending & (params.depart_s <= now_s[:, None] + 1e-9)  # (E, V)
    if not due.any():
        return
    length_m = hw.sim.vehicle_length_m
    entered = np.zeros_like(due)
    for e in np.flatnonzero(due.any(axis=1)):
        waiting = state.pending[e]
        for lane in np.unique(state.lane_to[e, due[e]]):
            # First come, first served per lane.
            first = np.flatnonzero(waiting & (state.lane_to[e] == lane))[0]
            if not due[e, first]:
                continue
            x0, v0 = state.x_m[e, first], state.speed_mps[e, first]
            in_lane = state.active[e] & ((state.lane_from[e] == lane) | (state.lane_to[e] == lane))
            ahead = in_lane & (state.x_m[e] > x0 - length_m)
            if ahead.any():
                j = np.flatnonzero(ahead)[np.argmin(state.x_m[e, ahead])]
                gap_m = state.x_m[e, j] - x0 - length_m
                need_m = params.idm.min_gap_m[e, first] + max(
                    0.0,
                    v0 * params.idm.headway_s[e, first]
                    + v0 * (v0 - state.speed_mps[e, j]) * params.inv_2_sqrt_ab_s2_per_m[e, first],
                )
                if gap_m < need_m:
                    continue
            entered[e, first] = True
    if not entered.any():
        return
    state.pending &= ~entered
    state.active |= entered
    state.is_cav &= ~entered  # a CAV drives itself until its first command
    state.cav_target_mps = np.where(entered, state.speed_mps, state.cav_target_mps)
    envs = entered.any(axis=1)
    caches.leaders_dirty |= envs
    refresh_road_facts(hw, envs)
    refresh_speed_bounds(hw)
