"""The highway backend's records as the shared :class:`~diacc.sim.state.TrafficState`.

What every backend reports (:mod:`diacc.sim.state`), read off the batch
records (:mod:`.simstate`) as copies, so a state handed on never changes
with the next step.
"""

from __future__ import annotations

import numpy as np

from diacc.sim.backends.highway.simstate import HighwaySim
from diacc.sim.state import TrafficState


def reported_lane(hw: HighwaySim) -> np.ndarray:
    """(E, V) reported lane: the one the centre is in, within the manoeuvre's two."""
    state = hw.state
    lo = np.minimum(state.lane_from, state.lane_to)
    hi = np.maximum(state.lane_from, state.lane_to)
    return np.minimum(np.maximum(np.floor(state.y_m / hw.road.lane_width_m), lo), hi)


def traffic_state(
    hw: HighwaySim,
    env: int | None,
    accel_mps2: np.ndarray,
    collisions: np.ndarray,
    arrivals: np.ndarray,
) -> TrafficState:
    """Every env's TrafficState as one (E, V) batch, or env ``env``'s alone as a batch of
    one (copies); ``accel_mps2`` is (E, V) (or (1, V)), ``collisions`` and ``arrivals``
    are (K, 3) rows (env, i, j) and (A, 2) rows (env, i) of the batch returned."""
    state, params = hw.state, hw.params
    rows = slice(None) if env is None else slice(env, env + 1)
    x_m = state.x_m[rows]
    shape = x_m.shape
    lane = reported_lane(hw)[rows]
    return TrafficState(
        time_s=state.time_s[rows].copy(),
        step=state.step_count[rows].copy(),
        vehicle_id=np.broadcast_to(np.arange(shape[1], dtype=np.int32), shape).copy(),
        x_m=x_m.copy(),
        y_m=state.y_m[rows].copy(),
        speed_mps=state.speed_mps[rows].copy(),
        accel_mps2=np.asarray(accel_mps2, dtype=np.float64).copy(),
        heading_rad=state.heading_rad[rows].copy(),
        lane=lane.astype(np.int16),
        segment=hw.tables.segment_of(x_m).astype(np.int16),
        length_m=np.full(shape, hw.sim.vehicle_length_m),
        width_m=np.full(shape, hw.sim.vehicle_width_m),
        is_cav=params.reported_cav[rows].copy(),
        style=params.style[rows].copy(),
        active=state.active[rows].copy(),
        arrived=state.arrived[rows].copy(),
        collisions=collisions,
        arrivals=arrivals,
    )
