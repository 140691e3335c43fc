"""Compact encoding of the per-step messages between SumoBackend and its worker.

A decision step is one round trip over the worker's pipe. Pickling the
reply, a :class:`~diacc.sim.state.TrafficState` dataclass of 16 small arrays,
and the command tuple costs about as much as all the Python work of the
worker's step; raw bytes cost a fraction of that (the SUMO backend's overhead
is in docs/benchmarks, "SUMO backend vs raw libsumo loop"). So the two
messages of every step travel as raw bytes:

* step request: :data:`STEP_REQUEST`, then ``lane_change`` as int8 and
  ``speed_change_mps`` as float64, one value per vehicle;
* state reply (to a step or a reset): :data:`STATE_REPLY`, a header
  (``time_s``; ``step``, vehicle, collision and arrival counts), then every
  array of :data:`~diacc.sim.state.FIELD_DTYPES` as raw bytes, widest dtype first,
  so that each array decodes as an aligned view of one buffer.

The rare messages (spec, reset, close, errors) stay pickled tuples. A pickle
(protocol 2 and later) starts with byte ``0x80``, so the one-byte tags below
never collide with it: :func:`is_step_request` and :func:`is_state_reply` tell
them apart.
"""

from __future__ import annotations

import struct

import numpy as np

from diacc.sim.state import FIELD_DTYPES, TrafficState

STEP_REQUEST = b"s"
STATE_REPLY = b"S"
#: Array fields in buffer order: widest item first keeps every offset aligned.
_FIELDS = sorted(FIELD_DTYPES, key=lambda name: -FIELD_DTYPES[name].itemsize)
#: time_s, then step and the vehicle, collision and arrival counts (40 bytes).
_HEADER = struct.Struct("<d4q")


def is_step_request(message: bytes) -> bool:
    return message[:1] == STEP_REQUEST


def is_state_reply(message: bytes) -> bool:
    return message[:1] == STATE_REPLY


def encode_step_request(lane_change: np.ndarray, speed_change_mps: np.ndarray) -> bytes:
    """``(V,)`` lane changes and speed changes as one message."""
    return b"".join(
        (
            STEP_REQUEST,
            np.asarray(lane_change, np.int8).tobytes(),
            np.asarray(speed_change_mps, np.float64).tobytes(),
        )
    )


def decode_step_request(message: bytes) -> tuple[np.ndarray, np.ndarray]:
    """``(lane_change (V,) int8, speed_change_mps (V,) float64)`` of a step request."""
    n = (len(message) - 1) // 9  # int8 + float64 per vehicle
    lane_change = np.frombuffer(message, np.int8, n, offset=1)
    return lane_change, np.frombuffer(message, np.float64, n, offset=1 + n)


def encode_state(state: TrafficState) -> bytes:
    """One message holding every field of ``state``, a batch of one (a copy: the state may
    change after); event rows go without their env column."""
    counts = (int(state.step[0]), state.n_vehicles, len(state.collisions), len(state.arrivals))
    parts = [STATE_REPLY, _HEADER.pack(float(state.time_s[0]), *counts)]
    events = {"collisions": state.collisions[:, 1:], "arrivals": state.arrivals[:, 1]}
    parts += [
        np.asarray(events.get(name, getattr(state, name)), FIELD_DTYPES[name]).tobytes()
        for name in _FIELDS
    ]
    return b"".join(parts)


def decode_state(message: bytes) -> TrafficState:
    """The :class:`TrafficState` of a state reply as a batch of one (what the backend
    returns); its per-vehicle arrays are writable views of one copy."""
    buffer = bytearray(memoryview(message)[1:])  # drop the tag: offsets start aligned
    time_s, step, n, n_collisions, n_arrivals = _HEADER.unpack_from(buffer)
    counts = {"collisions": 2 * n_collisions, "arrivals": n_arrivals}
    sizes = [counts.get(name, n) * FIELD_DTYPES[name].itemsize for name in _FIELDS]
    if _HEADER.size + sum(sizes) != len(buffer):
        raise ValueError(
            f"state reply of {len(buffer)} bytes, expected {_HEADER.size + sum(sizes)}"
        )
    offset = _HEADER.size
    arrays = {}
    for name, size in zip(_FIELDS, sizes, strict=True):
        arrays[name] = np.frombuffer(buffer, FIELD_DTYPES[name], counts.get(name, n), offset)
        offset += size
    # The worker's one simulation as a batch of one: env 0 in front of each event row.
    pairs = arrays.pop("collisions").reshape(n_collisions, 2)
    arrivals = arrays.pop("arrivals")
    return TrafficState(
        time_s=np.array([time_s]),
        step=np.array([step], np.int64),
        collisions=np.hstack([np.zeros((n_collisions, 1), np.int32), pairs]),
        arrivals=np.stack([np.zeros(n_arrivals, np.int32), arrivals], axis=1),
        **{name: values.reshape(1, n) for name, values in arrays.items()},
    )
