"""Bring your own controller: ``diacc eval --policy package.module:factory``.

A user's controller drives the CAVs the way a PettingZoo user drives them:
it gets the dict of agent -> observation that ``diacc.parallel_env`` returns
(the ``"dict"`` format of :mod:`diacc.envs.spaces`) and returns a dict of
agent -> action (0 remain, 1 left, 2 right, 3 accelerate, 4 decelerate;
an agent left out remains, as in ``env.step``). ``factory()`` returns either

* a callable ``controller(observations) -> actions``, or
* an object with ``act(observations) -> actions`` and, optionally,
  ``reset(seed)``, called before every episode with the episode seed (so a
  controller with memory or its own random draws stays deterministic).

Like the scripted ``heuristic``, it runs under PSAR (``--psar-*`` apply), so
its requests are checked against the same safety filter as every CAV
policy's. The module is imported from the current directory or
``PYTHONPATH`` in every worker process (the spec string is what travels).
"""

from __future__ import annotations

import importlib
import os
import re
import sys
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from diacc.envs.actions import ACTION_NAMES
from diacc.envs.observation import ActorObs
from diacc.errors import DiaccError


class ControllerError(DiaccError, ValueError):
    """A user's controller cannot be loaded, or answers something that is not actions."""


#: ``package.module:factory``: what ``--policy`` takes for a user's controller.
SPEC_PATTERN = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*")


def is_user_spec(name: str) -> bool:
    """Whether a ``--policy`` value names a Python factory (not a file, not a baseline)."""
    return SPEC_PATTERN.fullmatch(name) is not None and not name.endswith(".pt")


def load_controller(spec: str) -> Any:
    """Import ``module`` and call ``factory()``; one-line :class:`PolicyError` on any fault."""
    if not is_user_spec(spec):
        raise ControllerError(
            f"--policy {spec!r}: a Python controller is given as package.module:factory"
        )
    module_name, factory_name = spec.split(":")
    if "" not in sys.path and os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # as `python -m` would: modules of the working directory
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - any import fault of user code is one line
        raise ControllerError(
            f"--policy {spec}: cannot import module {module_name!r} "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None
    factory = getattr(module, factory_name, None)
    if factory is None or not callable(factory):
        raise ControllerError(
            f"--policy {spec}: module {module_name!r} has no callable {factory_name!r}"
        )
    try:
        controller = factory()
    except Exception as exc:  # noqa: BLE001 - the user's factory failing is one line
        raise ControllerError(
            f"--policy {spec}: {factory_name}() raised {type(exc).__name__}: {exc}"
        ) from None
    if not callable(getattr(controller, "act", None)) and not callable(controller):
        raise ControllerError(
            f"--policy {spec}: {factory_name}() returned {type(controller).__name__}, which is "
            "neither callable nor has an act(observations) method"
        )
    return controller


class Controller:
    """A loaded controller, turned into the evaluator's arrays (the module docstring)."""

    def __init__(self, spec: str) -> None:
        self.spec = spec
        self.controller = load_controller(spec)
        act = getattr(self.controller, "act", None)
        self._act: Callable[[Mapping[str, Any]], Any] = act if callable(act) else self.controller

    def reset(self, seed: int) -> None:
        """Call the controller's ``reset(seed)``, if it has one."""
        reset = getattr(self.controller, "reset", None)
        if callable(reset):
            reset(seed)

    def actions(self, env, actor_obs: ActorObs) -> np.ndarray:
        """(C,) int64 actions of every agent slot of ``env`` (a
        :class:`~diacc.envs.env.BottleneckEnv` whose current step ``actor_obs`` is)."""
        actions = self._act(env.agent_observations(actor_obs))
        if not isinstance(actions, Mapping):
            raise ControllerError(
                f"{self.spec} returned {type(actions).__name__}; a controller returns a dict "
                "of agent -> action"
            )
        slots = env.agent_slots()
        batch = np.zeros(actor_obs.alive.shape[0], np.int64)  # (C,) remain unless told
        for agent, action in actions.items():
            if agent not in slots:
                raise ControllerError(
                    f"{self.spec} returned an action for {agent!r}, which is not on the road"
                )
            if not isinstance(action, (int, np.integer)) or not 0 <= action < len(ACTION_NAMES):
                raise ControllerError(
                    f"{self.spec} returned action {action!r} for {agent}; actions are "
                    f"0..{len(ACTION_NAMES) - 1} ({', '.join(ACTION_NAMES)})"
                )
            batch[slots[agent]] = int(action)
        return batch
