"""TrafficState: the arrays every backend returns after reset and each step.

Coordinate convention (identical for all backends)
---------------------------------------------------
* ``x_m``: longitudinal position of the vehicle's *centre* along the route,
  metres from the route start (0 .. ``Map.length_m``).
* ``y_m``: lateral position of the vehicle's centre, metres to the *left* of
  the right edge of the widest cross-section. The centre line of absolute
  lane ``l`` is at ``(l + 0.5) * lane_width_m`` (see :mod:`diacc.sim.maps`).
* ``heading_rad``: angle to the route direction, positive when turning left
  (counter-clockwise with x forward and y left).
* ``lane``: absolute lane index, 0 = rightmost lane of the widest section.
* ``segment``: index into ``Map.segments``.
* Vehicle index ``i`` is the vehicle's stable id for the whole episode
  (``vehicle_id[i] == i``); arrays have fixed capacity ``n_vehicles``.

A vehicle is ``active`` while it is on the road. It becomes ``arrived`` when
its centre passes the route end, and is then inactive for ever; its other
fields keep their last values. In a ``demand`` scenario a vehicle that has
not entered yet is *pending*: neither active nor arrived, at its entry slot
(:mod:`diacc.sim.scenario`). Inactive entries must be masked by consumers.

Batches
-------
A TrafficState is always a batch of E environments of the same scenario
(E = 1 for one env): every per-vehicle array is (E, V), each env its own
row; ``time_s`` and ``step`` are (E,) arrays; ``collisions`` rows are
(env, i, j) and ``arrivals`` rows (env, i). Every backend returns batches
(:mod:`diacc.sim.backends.base`); they join with :meth:`TrafficState.concat`,
split with :meth:`TrafficState.rows` and :meth:`TrafficState.env` (an E = 1
batch), the operations of every batched record (:class:`~diacc.records.Batched`).
Functions that read states index vehicles with :func:`take` and broadcast over
the env axis. Users who want one env's (V,) arrays index
row 0 of an E = 1 batch (``state.x_m[0]``), as the PettingZoo env and the
tutorials show.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from diacc.records import Batched, env_events, per_env


@dataclass
class TrafficState(Batched):
    """Arrays describing every vehicle of E simulations at one instant each (a
    :class:`~diacc.records.Batched` record: joined, selected and cut by env as declared)."""

    time_s: np.ndarray = per_env("E")  # float64
    step: np.ndarray = per_env("E")  # int
    vehicle_id: np.ndarray = per_env("E, V")  # int32, each row == arange(V)
    x_m: np.ndarray = per_env("E, V")  # float64 centre, along the route
    y_m: np.ndarray = per_env("E, V")  # float64 centre, left of the right road edge
    speed_mps: np.ndarray = per_env("E, V")  # float64
    accel_mps2: np.ndarray = per_env("E, V")  # float64 over the last step (0 at reset)
    heading_rad: np.ndarray = per_env("E, V")  # float64
    lane: np.ndarray = per_env("E, V")  # int16 absolute lane, 0 = rightmost
    segment: np.ndarray = per_env("E, V")  # int16 index into Map.segments
    length_m: np.ndarray = per_env("E, V")  # float64
    width_m: np.ndarray = per_env("E, V")  # float64
    is_cav: np.ndarray = per_env("E, V")  # bool
    style: np.ndarray = per_env("E, V")  # int8: 0 aggressive, 1 normal, 2 cautious, -1 CAV
    active: np.ndarray = per_env("E, V")  # bool, on the road now
    arrived: np.ndarray = per_env("E, V")  # bool, has left at the route end
    collisions: np.ndarray = env_events("env, i, j")  # (K, 3) int32: i and j collided this step
    arrivals: np.ndarray = env_events("env, i")  # (A, 2) int32: i arrived this step

    @property
    def n_vehicles(self) -> int:
        return int(self.vehicle_id.shape[-1])

    @property
    def n_envs(self) -> int:
        """E, the envs of a batch (its ``time_s`` is (E,))."""
        return len(self.time_s)

    @property
    def collided(self) -> np.ndarray:
        """(E, V) bool: vehicle took part in a collision this step."""
        out = np.zeros(self.vehicle_id.shape, dtype=bool)
        out[self.collisions[:, 0], self.collisions[:, 1]] = True
        out[self.collisions[:, 0], self.collisions[:, 2]] = True
        return out

    @property
    def collided_with(self) -> np.ndarray:
        """(E, V, V) bool, symmetric: vehicles i and j collided with each other this step."""
        out = np.zeros(self.vehicle_id.shape + self.vehicle_id.shape[-1:], dtype=bool)
        env, i, j = self.collisions.T  # rows (env, i, j)
        out[env, i, j] = True
        out[env, j, i] = True
        return out

    @property
    def arrived_now(self) -> np.ndarray:
        """(E, V) bool: vehicle arrived at the route end this step (``arrivals``)."""
        out = np.zeros(self.vehicle_id.shape, dtype=bool)
        out[self.arrivals[:, 0], self.arrivals[:, 1]] = True
        return out

    def vehicles(self, lo: int, hi: int) -> TrafficState:
        """Vehicles ``lo:hi`` alone (views; vehicle ``lo + i`` is index ``i`` here), without
        collision or arrival rows: for per-vehicle work restricted to
        :func:`on_road_window`."""
        per_vehicle = {name: getattr(self, name)[..., lo:hi] for name in PER_VEHICLE_FIELDS}
        return TrafficState(
            time_s=self.time_s,
            step=self.step,
            collisions=np.zeros((0, 3), np.int32),
            arrivals=np.zeros((0, 2), np.int32),
            **per_vehicle,
        )


def on_road_window(active: np.ndarray) -> tuple[int, int]:
    """Smallest vehicle index window ``lo:hi`` holding every vehicle on the road.

    ``active`` is a batch's (E, V); the window is the union over the
    envs, ``(0, 0)`` when no vehicle is on the road. Vehicles enter in index
    order and leave roughly so, so in a demand episode (hundreds of vehicles,
    a few dozen on the road) work restricted to the window scales with the
    vehicles on the road, not with V.
    """
    on_road = active.reshape(-1, active.shape[-1]).any(axis=0)  # (V,)
    if not on_road.any():
        return 0, 0
    return int(np.argmax(on_road)), on_road.size - int(np.argmax(on_road[::-1]))


def take(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``values[e, idx[e, ...]]`` per env of a batch's (E, V) values: idx is (E, ...).

    Indices are vehicle indices (>= 0): a batch is read through one flat index,
    a fraction of the cost of indexing by env and vehicle (PSAR, the
    observations and the reward take rows about a hundred times per step).
    """
    idx = np.asarray(idx)
    base = flat_offsets(values.shape[:1], values.shape[1], idx.ndim - 1)
    return np.ascontiguousarray(values).reshape(-1).take(idx + base)


def take_last(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``np.take_along_axis(values, idx, -1)`` for non-negative ``idx`` (..., K) with the
    leading shape of ``values`` (..., N), through one flat index: a fraction of its cost
    on the small arrays of a step, where it runs dozens of times."""
    base = flat_offsets(idx.shape[:-1], values.shape[-1], 1)  # (..., 1)
    return np.ascontiguousarray(values).reshape(-1).take(idx + base)


def take_rows(values: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Rows ``idx`` (..., R) of per-vehicle rows ``values`` (..., V, K): (..., R, K)
    (``np.take_along_axis(values, idx[..., None], -2)``, through one flat row index)."""
    base = flat_offsets(idx.shape[:-1], values.shape[-2], 1)  # (..., 1)
    flat_rows = np.ascontiguousarray(values).reshape(-1, values.shape[-1])
    return flat_rows.take(idx + base, axis=0)


def stack_last(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """``np.stack(arrays, -1)`` of same-shape arrays (..., ) -> (..., K), written into one
    new array: a third of ``np.stack``'s cost on the small arrays of a step."""
    out = np.empty(arrays[0].shape + (len(arrays),), np.result_type(*arrays))
    for k, values in enumerate(arrays):
        out[..., k] = values
    return out


@functools.lru_cache(maxsize=256)
def flat_offsets(lead: tuple[int, ...], stride: int, trailing: int) -> np.ndarray:
    """``lead + (1,) * trailing`` first flat index of each leading entry's block of
    ``stride`` values: added to indices within the blocks, it indexes the flattened
    array, so one ``ndarray.take`` replaces fancy indexing by env (or row) and
    vehicle, at a fraction of its cost (cached; read-only)."""
    offsets = (np.arange(math.prod(lead)) * stride).reshape(lead + (1,) * trailing)
    offsets.flags.writeable = False
    return offsets


#: dtype of every array field; backends must produce exactly these.
FIELD_DTYPES: dict[str, np.dtype] = {
    "vehicle_id": np.dtype(np.int32),
    "x_m": np.dtype(np.float64),
    "y_m": np.dtype(np.float64),
    "speed_mps": np.dtype(np.float64),
    "accel_mps2": np.dtype(np.float64),
    "heading_rad": np.dtype(np.float64),
    "lane": np.dtype(np.int16),
    "segment": np.dtype(np.int16),
    "length_m": np.dtype(np.float64),
    "width_m": np.dtype(np.float64),
    "is_cav": np.dtype(bool),
    "style": np.dtype(np.int8),
    "active": np.dtype(bool),
    "arrived": np.dtype(bool),
    "collisions": np.dtype(np.int32),
    "arrivals": np.dtype(np.int32),
}


#: The fields with one entry per vehicle, (E, V).
PER_VEHICLE_FIELDS = tuple(name for name in FIELD_DTYPES if name not in ("collisions", "arrivals"))


def validate_state(state: TrafficState) -> None:
    """Raise ``AssertionError`` if a batch breaks the shared conventions."""
    n_envs, n = state.n_envs, state.n_vehicles
    for name in ("time_s", "step"):
        shape = np.shape(getattr(state, name))
        assert shape == (n_envs,), f"{name} has shape {shape}, expected ({n_envs},)"
    for name, dtype in FIELD_DTYPES.items():
        arr = getattr(state, name)
        assert isinstance(arr, np.ndarray), f"{name} is not an array"
        assert arr.dtype == dtype, f"{name} has dtype {arr.dtype}, expected {dtype}"
        if name in ("collisions", "arrivals"):
            width = 3 if name == "collisions" else 2
            assert arr.shape[1:] == (width,), f"{name} has shape {arr.shape}, expected (K, {width})"
            assert np.all((arr[:, 0] >= 0) & (arr[:, 0] < n_envs)), f"{name} names a missing env"
        else:
            expected = (n_envs, n)
            assert arr.shape == expected, f"{name} has shape {arr.shape}, expected {expected}"
    assert np.all(state.vehicle_id == np.arange(n)), "vehicle_id must equal arange(V) in every env"
    assert not np.any(state.active & state.arrived), "a vehicle is both active and arrived"
