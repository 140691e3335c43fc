"""Test helpers shared by the test modules: hand-built TrafficStates.

Import with ``from helpers import make_state`` (pytest puts ``tests/`` on
``sys.path`` because the folder has no ``__init__.py``).
"""

from __future__ import annotations

import copy
import dataclasses
import types
from collections.abc import Callable, Sequence

import numpy as np

from diacc.config import CAV_STYLE, NORMAL
from diacc.sim.state import PER_VEHICLE_FIELDS, TrafficState, validate_state


def make_state(
    x_m: Sequence[float],
    lane: Sequence[int],
    speed_mps: Sequence[float] | float = 20.0,
    *,
    is_cav: Sequence[bool] | bool = False,
    heading_rad: Sequence[float] | float = 0.0,
    accel_mps2: Sequence[float] | float = 0.0,
    active: Sequence[bool] | bool = True,
    arrived: Sequence[bool] | bool = False,
    segment: Sequence[int] | int = 0,
    length_m: Sequence[float] | float = 5.0,
    width_m: Sequence[float] | float = 1.8,
    lane_width_m: float = 3.2,
    y_m: Sequence[float] | None = None,
    collisions: Sequence[tuple[int, int]] = (),
    arrivals: Sequence[int] = (),
    time_s: float = 0.0,
    step: int = 0,
) -> TrafficState:
    """Build a valid :class:`TrafficState`, a batch of one env (E = 1), from per-vehicle
    lists or scalars.

    Scalars are broadcast to every vehicle. ``y_m`` defaults to the centre of
    each vehicle's lane; ``collisions`` are (i, j) pairs and ``arrivals`` vehicle
    indices of the one env. The result passes :func:`diacc.sim.state.validate_state`.
    """
    n = len(x_m)

    def col(value, dtype) -> np.ndarray:
        arr = np.broadcast_to(np.asarray(value), (n,)).astype(dtype)
        return arr[None].copy()  # (1, V)

    lane_arr = col(lane, np.int16)
    cav = col(is_cav, bool)
    state = TrafficState(
        time_s=np.array([float(time_s)]),
        step=np.array([int(step)]),
        vehicle_id=np.arange(n, dtype=np.int32)[None],
        x_m=col(x_m, np.float64),
        y_m=(lane_arr + 0.5) * lane_width_m if y_m is None else col(y_m, np.float64),
        speed_mps=col(speed_mps, np.float64),
        accel_mps2=col(accel_mps2, np.float64),
        heading_rad=col(heading_rad, np.float64),
        lane=lane_arr,
        segment=col(segment, np.int16),
        length_m=col(length_m, np.float64),
        width_m=col(width_m, np.float64),
        is_cav=cav,
        style=np.where(cav, CAV_STYLE, NORMAL).astype(np.int8),
        active=col(active, bool),
        arrived=col(arrived, bool),
        collisions=np.pad(np.asarray(collisions, dtype=np.int32).reshape(-1, 2), ((0, 0), (1, 0))),
        arrivals=np.pad(np.asarray(arrivals, dtype=np.int32).reshape(-1, 1), ((0, 0), (1, 0))),
    )
    state.y_m = state.y_m.astype(np.float64)
    validate_state(state)
    return state


def first_env(value):
    """Env 0 of every array in ``value`` (an array, a tuple, a NamedTuple or a dataclass of
    them): the one env's view of a function's output on an E = 1 batch. A TrafficState
    becomes a namespace of its (V,) rows, (K, 2) ``collisions`` and (A,) ``arrivals``
    (for scalar reference code; no TrafficState has that form)."""
    if isinstance(value, TrafficState):
        rows = {name: getattr(value, name)[0] for name in (*PER_VEHICLE_FIELDS, "time_s", "step")}
        rows.update(collisions=value.collisions[:, 1:], arrivals=value.arrivals[:, 1])
        return types.SimpleNamespace(**rows, n_vehicles=value.n_vehicles)
    if isinstance(value, np.ndarray):
        return value[0] if value.shape else value
    if isinstance(value, tuple):
        rows = [first_env(v) for v in value]
        return type(value)(*rows) if hasattr(value, "_fields") else tuple(rows)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        out = copy.copy(value)
        for f in dataclasses.fields(value):
            object.__setattr__(out, f.name, first_env(getattr(value, f.name)))
        return out
    return value


def one_env(fn: Callable) -> Callable:
    """``fn(state, *arrays, ...)`` of a batch, for one env's arrays: called on an E = 1
    ``state`` with every array argument given the env axis ((C,) -> (1, C)), it returns
    :func:`first_env` of the result (what the single-env tests compare)."""

    def call(state: TrafficState, *args, **kwargs):
        args = [a[None] if isinstance(a, np.ndarray) else a for a in args]
        kwargs = {k: v[None] if isinstance(v, np.ndarray) else v for k, v in kwargs.items()}
        return first_env(fn(state, *args, **kwargs))

    return call


#: A 160 m map (3 lanes, then a 25 % reduction) for tiny training and demand runs.
SHORT_MAP = """
name = "short"
lane_width_m = 3.2
[[segments]]
kind = "multilane"
length_m = 100
lanes = 3
speed_limit_mps = 25.0
[[segments]]
kind = "reduction25"
length_m = 60
lanes = 2
speed_limit_mps = 25.0
"""
