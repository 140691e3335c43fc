"""The highway backend's records as the shared :class:`~diacc.sim.state.TrafficState`.

What every backend reports (:mod:`diacc.sim.state`), read off the batch
records (:mod:`.simstate`) as copies, so a state handed on never changes
with the next step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from diacc.sim.state import TrafficState

if TYPE_CHECKING:
    from diacc.sim.backends.highway.backend import HighwayBackend


def reported_lane(hw: HighwayBackend) -> np.ndarray:
    """(E, V) reported lane: the one the centre is in, within the manoeuvre's two."""
    state = hw.state
    lo = np.minimum(state.lane_from, state.lane_to)
    hi = np.maximum(state.lane_from, state.lane_to)
    return np.minimum(np.maximum(np.floor(state.y_m / hw.road.lane_width_m), lo), hi)


def env_traffic_state(
    hw: HighwayBackend,
    e: int,
    lane: np.ndarray,
    accel_mps2: np.ndarray,
    collisions: np.ndarray,
    arrivals: np.ndarray,
) -> TrafficState:
    """Env ``e``'s TrafficState (copies of its rows); ``lane`` is :func:`reported_lane`."""
    state, params = hw.state, hw.params
    n = state.x_m.shape[1]
    return TrafficState(
        time_s=float(state.time_s[e]),
        step=int(state.step_count[e]),
        vehicle_id=np.arange(n, dtype=np.int32),
        x_m=state.x_m[e].copy(),
        y_m=state.y_m[e].copy(),
        speed_mps=state.speed_mps[e].copy(),
        accel_mps2=np.asarray(accel_mps2, dtype=np.float64).copy(),
        heading_rad=state.heading_rad[e].copy(),
        lane=lane[e].astype(np.int16),
        segment=hw.tables.segment_of(state.x_m[e]).astype(np.int16),
        length_m=np.full(n, hw.sim.vehicle_length_m),
        width_m=np.full(n, hw.sim.vehicle_width_m),
        is_cav=params.reported_cav[e].copy(),
        style=params.style[e].copy(),
        active=state.active[e].copy(),
        arrived=state.arrived[e].copy(),
        collisions=collisions.astype(np.int32).reshape(-1, 2),
        arrivals=arrivals.astype(np.int32),
    )


def batch_traffic_state(
    hw: HighwayBackend, accel_mps2: np.ndarray, collisions: np.ndarray, arrivals: np.ndarray
) -> TrafficState:
    """Every env's TrafficState as one (E, V) batch (copies); rows (env, i, j) and (env, i)."""
    state, params = hw.state, hw.params
    shape = state.x_m.shape
    return TrafficState(
        time_s=state.time_s.copy(),
        step=state.step_count.copy(),
        vehicle_id=np.broadcast_to(np.arange(shape[1], dtype=np.int32), shape).copy(),
        x_m=state.x_m.copy(),
        y_m=state.y_m.copy(),
        speed_mps=state.speed_mps.copy(),
        accel_mps2=np.asarray(accel_mps2, dtype=np.float64).copy(),
        heading_rad=state.heading_rad.copy(),
        lane=reported_lane(hw).astype(np.int16),
        segment=hw.tables.segment_of(state.x_m).astype(np.int16),
        length_m=np.full(shape, hw.sim.vehicle_length_m),
        width_m=np.full(shape, hw.sim.vehicle_width_m),
        is_cav=params.reported_cav.copy(),
        style=params.style.copy(),
        active=state.active.copy(),
        arrived=state.arrived.copy(),
        collisions=collisions,
        arrivals=arrivals,
    )
