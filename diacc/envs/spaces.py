"""The observation and state spaces diacc shows to PettingZoo and its wrappers.

Internally an agent's observation is a row of :class:`~diacc.envs.observation.ActorObs`
(boolean masks, a 0-d ``alive`` flag, int64 action codes). Wrappers are
stricter than PettingZoo's own API test: TorchRL builds its specs from
``MultiBinary.n`` and fails on a tuple or a 0-d shape, SuperSuit's
``black_death`` and SB3 need one flat ``Box``. So the spaces here are:

* ``"dict"`` (default): a ``Dict`` of ``Box`` (floats, action codes) and
  integer ``MultiBinary(n)`` (masks, int8 0/1); ``alive`` is ``MultiBinary(1)``.
  The graph structure (neighbour nodes, masks, history) stays visible.
* ``"flat"``: one float32 ``Box`` holding the same values, laid out by
  ``gymnasium.spaces.flatten`` of the ``Dict`` space (keys in its sorted
  order); :func:`unflatten` gives the dict back, so the graph structure is
  one call away for those who want it.

The centralised critic's view, :meth:`BottleneckEnv.state`, is a float32
``Box`` (:func:`state_space`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import fields

import gymnasium
import numpy as np

from diacc.envs.observation import ActorObs, ObservationSpec
from diacc.errors import DiaccError

#: Observation formats of :class:`~diacc.envs.env.BottleneckEnv` (``observation_format``).
OBSERVATION_FORMATS = ("dict", "flat")
#: Field order of an agent's observation (and of the flat vector).
FIELD_ORDER = tuple(f.name for f in fields(ActorObs))


class SpaceError(DiaccError, ValueError):
    """An observation that does not fit the space it claims to be from; one line."""


def check_format(observation_format: str) -> str:
    """``observation_format`` if it is one of :data:`OBSERVATION_FORMATS`, else a one-line error."""
    if observation_format not in OBSERVATION_FORMATS:
        raise SpaceError(
            f"unknown observation_format {observation_format!r}; "
            f"use one of: {', '.join(OBSERVATION_FORMATS)}"
        )
    return observation_format


def _row_shapes(spec: ObservationSpec) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """One agent's field shapes; the 0-d ``alive`` becomes (1,) for ``MultiBinary(1)``."""
    shapes = {}
    for name, (shape, dtype) in spec.actor_shapes(n_cavs=1).items():
        shapes[name] = (shape[1:] or (1,), dtype)
    return shapes


def dict_space(spec: ObservationSpec) -> gymnasium.spaces.Dict:
    """One agent's observation space in the ``"dict"`` format."""
    spaces: dict[str, gymnasium.spaces.Space] = {}
    for name, (shape, dtype) in _row_shapes(spec).items():
        if dtype == np.dtype(bool):
            (n,) = shape  # every mask is one axis: an integer n, as TorchRL requires
            spaces[name] = gymnasium.spaces.MultiBinary(n)
        elif dtype == np.int64:  # action codes
            spaces[name] = gymnasium.spaces.Box(0, spec.n_actions - 1, shape, np.int64)
        else:
            spaces[name] = gymnasium.spaces.Box(-np.inf, np.inf, shape, np.float32)
    return gymnasium.spaces.Dict({name: spaces[name] for name in FIELD_ORDER})


def flat_space(spec: ObservationSpec) -> gymnasium.spaces.Box:
    """One agent's observation space in the ``"flat"`` format: float32 (D,)."""
    flat = gymnasium.spaces.flatten_space(dict_space(spec))
    return gymnasium.spaces.Box(
        flat.low.astype(np.float32), flat.high.astype(np.float32), flat.shape, np.float32
    )


def observation_space(spec: ObservationSpec, observation_format: str) -> gymnasium.spaces.Space:
    """The space of one agent's observation in ``observation_format``."""
    if check_format(observation_format) == "flat":
        return flat_space(spec)
    return dict_space(spec)


def state_space(spec: ObservationSpec) -> gymnasium.spaces.Box:
    """The space of :meth:`BottleneckEnv.state`: every critic field, flattened, float32."""
    size = sum(int(np.prod(shape)) for shape, _ in spec.critic_shapes().values())
    return gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32)


def agent_observation(
    actor_obs: ActorObs, i: int, space: gymnasium.spaces.Dict, observation_format: str
) -> dict[str, np.ndarray] | np.ndarray:
    """Agent ``i``'s row of ``actor_obs`` as a member of its space (dtypes cast, ``alive`` (1,))."""
    row = {
        name: np.asarray(getattr(actor_obs, name)[i], dtype=space[name].dtype).reshape(
            space[name].shape
        )
        for name in FIELD_ORDER
    }
    if observation_format == "flat":
        return gymnasium.spaces.flatten(space, row).astype(np.float32)
    return row


def unflatten(spec: ObservationSpec, flat: np.ndarray) -> dict[str, np.ndarray]:
    """The ``"dict"`` observation held in a ``"flat"`` one (D,)."""
    space = dict_space(spec)
    flat = np.asarray(flat)
    expected = gymnasium.spaces.flatdim(space)
    if flat.shape != (expected,):
        raise SpaceError(f"a flat observation has shape ({expected},), got {flat.shape}")
    return gymnasium.spaces.unflatten(space, flat)


def actor_obs_from_rows(
    spec: ObservationSpec, rows: list[Mapping[str, np.ndarray] | np.ndarray]
) -> ActorObs:
    """Stack agents' observations (dict or flat) back into an :class:`ActorObs` (C = len(rows)).

    The inverse of :func:`agent_observation`: masks become bool again and
    ``alive`` a (C,) vector, as the networks expect.
    """
    shapes = spec.actor_shapes(n_cavs=len(rows))
    dicts = [unflatten(spec, r) if isinstance(r, np.ndarray) else r for r in rows]
    out = {}
    for name, (shape, dtype) in shapes.items():
        try:
            values = [np.asarray(d[name]) for d in dicts]
        except KeyError:
            raise SpaceError(f"observation has no field {name!r}") from None
        out[name] = np.stack(values).astype(dtype).reshape(shape)
    return ActorObs(**out)
