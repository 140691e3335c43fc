"""Checks of what a Python caller hands the environment: the same one-line errors as the CLI.

PettingZoo users call :meth:`~diacc.envs.env.BottleneckEnv.reset` and
:meth:`~diacc.envs.env.BottleneckEnv.step` directly. Without these checks an
action for an agent that does not exist was dropped, a float action was cut
to an integer, a step after the episode's end ran on, and ``step(None)`` died
in an ``AttributeError`` deep inside. Each check raises :class:`EnvCallError`
(a ``ValueError``), or for a wrong type its subclass :class:`EnvCallTypeError`
(also a ``TypeError``), with a message naming the argument.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from diacc.envs.actions import ACTION_NAMES
from diacc.errors import DiaccError

#: Largest seed: numpy's and SUMO's seeds are 32-bit.
MAX_SEED = 2**32 - 1


class EnvCallError(DiaccError, ValueError):
    """An argument of an environment call has a value the environment cannot take."""


class EnvCallTypeError(EnvCallError, TypeError):
    """An argument of an environment call has the wrong type (also an :class:`EnvCallError`)."""


def _is_int(value: object) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def check_seed(seed: object) -> int | None:
    """``seed`` as an int (``None`` stays ``None``); one line unless a whole number in range."""
    if seed is None:
        return None
    if not _is_int(seed):
        raise EnvCallTypeError(f"reset(seed=...) takes a whole number, got {seed!r}")
    if not 0 <= seed <= MAX_SEED:
        raise EnvCallError(f"reset(seed=...) must be in [0, {MAX_SEED}], got {seed}")
    return int(seed)


def check_action(agent: str, action: object) -> int:
    """One agent's action as an int; one line unless one of the action codes."""
    if isinstance(action, np.ndarray) and action.shape == ():
        action = action[()]
    if not _is_int(action):
        raise EnvCallTypeError(
            f"the action of {agent} is {action!r}; actions are whole numbers "
            f"0..{len(ACTION_NAMES) - 1}"
        )
    if not 0 <= action < len(ACTION_NAMES):
        raise EnvCallError(
            f"the action of {agent} is {action}; actions are 0..{len(ACTION_NAMES) - 1} "
            f"({', '.join(ACTION_NAMES)})"
        )
    return int(action)


def check_actions(actions: object, agents: list[str], possible: list[str]) -> dict[str, int]:
    """``step``'s argument, as the actions of the agents on the road now.

    A mapping of agent names to action codes; a name that is no agent of the env
    is refused. An agent that has left (its last observation came with its
    termination, and a loop that acts on every observation acts for it once more)
    is ignored, as PettingZoo loops expect.
    """
    if not isinstance(actions, Mapping):
        raise EnvCallTypeError(
            f"step() takes a dict of agent name -> action, got {type(actions).__name__}"
        )
    known = set(possible)
    for agent in actions:
        if agent not in known:
            raise EnvCallError(
                f"step() got an action for {agent!r}, which is not an agent of this env "
                f"(agents now: {', '.join(agents) or 'none'})"
            )
    checked = {agent: check_action(agent, action) for agent, action in actions.items()}
    live = set(agents)
    return {agent: action for agent, action in checked.items() if agent in live}


def check_action_array(actions: object, n_slots: int) -> np.ndarray:
    """``step_arrays``'s argument: (C,) integer action codes."""
    array = np.asarray(actions)
    if array.shape != (n_slots,) or array.dtype.kind not in "iu":
        raise EnvCallTypeError(
            f"step_arrays() takes ({n_slots},) integer actions, got shape {array.shape} "
            f"of {array.dtype}"
        )
    if array.size and not (0 <= array.min() and array.max() < len(ACTION_NAMES)):
        raise EnvCallError(f"step_arrays() got actions outside 0..{len(ACTION_NAMES) - 1}")
    return array
