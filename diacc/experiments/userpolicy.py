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

Its answers follow the rules of ``env.step`` (:func:`diacc.envs.api_checks.check_action`:
whole numbers 0..4, a 0-d integer array too, never ``True``). A bug of the user's
inside ``act`` or ``reset`` is the user's traceback (from their own frame on) and
one line of ours naming the controller, the cell and the step
(:class:`ControllerFault`); a call that does not return within ``timeout_s``
(``--controller-timeout``, :data:`DEFAULT_TIMEOUT_S`) is stopped the same way.
"""

from __future__ import annotations

import importlib
import os
import re
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np

from diacc.envs.api_checks import EnvCallError, check_action
from diacc.envs.observation import ActorObs
from diacc.errors import DiaccError


class ControllerError(DiaccError, ValueError):
    """A user's controller cannot be loaded, or answers something that is not actions."""


class ControllerFault(ControllerError):
    """The user's ``act`` or ``reset`` raised or did not return in time.

    The message is our one line (controller, cell, step); ``user_traceback`` is the
    user's exception from their own frame on, text, so that it survives the trip from
    a worker process, where the chained ``__cause__`` is lost. The CLI prints it above
    the line.
    """

    def __init__(self, message: str, user_traceback: str = "") -> None:
        super().__init__(message)
        self.user_traceback = user_traceback


class _Expired(BaseException):
    """The time limit of a controller call ran out (a BaseException, so that a user's
    ``except Exception`` inside the call cannot swallow it)."""


#: Longest a controller's ``act`` or ``reset`` may run by default (s): far beyond any
#: sane decision, short of a forgotten evaluation (``--controller-timeout``, 0: none).
DEFAULT_TIMEOUT_S = 60.0


@contextmanager
def _time_limit(seconds: float) -> Iterator[None]:
    """Raise :class:`_Expired` in the block after ``seconds`` (SIGALRM: only in a main
    thread, which runs every evaluation but a Ray task's; elsewhere, and with 0, no limit)."""
    if seconds <= 0 or threading.current_thread() is not threading.main_thread():
        yield
        return

    def expire(signum, frame) -> None:
        raise _Expired

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


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
    """A loaded controller, turned into the evaluator's arrays (the module docstring).

    ``cell`` names the cell of the episodes to come in its errors (set by the policy);
    ``timeout_s`` limits each ``act`` and ``reset`` call (0: no limit).
    """

    def __init__(self, spec: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.spec = spec
        self.timeout_s = timeout_s
        self.cell = "?"
        self.controller = load_controller(spec)
        act = getattr(self.controller, "act", None)
        self._act: Callable[[Mapping[str, Any]], Any] = act if callable(act) else self.controller

    def reset(self, seed: int) -> None:
        """Call the controller's ``reset(seed)``, if it has one."""
        reset = getattr(self.controller, "reset", None)
        if callable(reset):
            self._call(reset, seed, what="reset(seed)", where=f"before the episode of seed {seed}")

    def _call(self, fn: Callable, argument: Any, what: str, where: str) -> Any:
        """``fn(argument)`` within the time limit; a user's fault as a :class:`ControllerFault`."""
        where = f"{where} in cell {self.cell}"
        try:
            with _time_limit(self.timeout_s):
                return fn(argument)
        except _Expired:
            raise ControllerFault(
                f"controller {self.spec}: {what} did not return within {self.timeout_s:g} s "
                f"{where} (--controller-timeout)"
            ) from None
        except Exception as exc:
            trace = traceback.format_exception(type(exc), exc, exc.__traceback__.tb_next)
            raise ControllerFault(
                f"controller {self.spec}: {what} raised {type(exc).__name__}: "
                f"{(str(exc).splitlines() or [''])[0]} {where}",
                "".join(trace),
            ) from exc

    def actions(self, env, actor_obs: ActorObs) -> np.ndarray:
        """(C,) int64 actions of every agent slot of ``env`` (a
        :class:`~diacc.envs.env.BottleneckEnv` whose current step ``actor_obs`` is)."""
        where = f"at step {env.steps}"
        actions = self._call(self._act, env.agent_observations(actor_obs), "act()", where)
        fault = f"controller {self.spec} {where} in cell {self.cell}:"
        if not isinstance(actions, Mapping):
            raise ControllerError(
                f"{fault} returned {type(actions).__name__}; a controller returns a dict of "
                "agent -> action"
            )
        slots = env.agent_slots()
        batch = np.zeros(actor_obs.alive.shape[0], np.int64)  # (C,) remain unless told
        for agent, action in actions.items():
            if agent not in slots:
                raise ControllerError(f"{fault} returned an action for {agent!r}, not on the road")
            try:
                batch[slots[agent]] = check_action(agent, action)  # env.step's rules
            except EnvCallError as exc:
                raise ControllerError(f"{fault} {exc}") from None
        return batch
