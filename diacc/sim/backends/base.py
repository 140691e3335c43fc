"""The Backend protocol: what every simulator behind diacc must offer.

A backend owns ``n_envs`` simulations (E, one unless it batches envs, as
``highway`` does) of one :class:`~diacc.sim.maps.Map`. Each env is reset with a
:class:`~diacc.sim.scenario.Scenario` and a seed; all are stepped together with
(E, V) commands for the CAVs (HDVs drive themselves), and every state returned is
a :class:`~diacc.sim.state.TrafficState` batch in the shared coordinate
convention: the reset env's as a batch of one, a step's as the (E, V) batch.
Everything past the backend (observations, PSAR, metrics, the viewer
:mod:`diacc.sim.viewer`) reads only that state, so nothing else needs to know
which simulator runs. Each backend is a package: ``highway/`` and ``sumo/``.

CAV command semantics, identical on every backend:

* ``lane_change[i]`` in {-1, 0, +1}: move one lane to the right (-1) or left
  (+1); the change completes within the step. A change towards a lane that
  does not exist at the vehicle's position is ignored.
* ``speed_change_mps[i]``: the CAV's target speed for the end of the step is
  its current speed plus this value, clipped to [0, speed limit]; it gets
  there at constant acceleration within the CAV's accel/decel limits.
  A CAV holds its speed when the change is 0: no built-in car following, so
  the policy and PSAR carry safety (SUMO ``speedMode 0``).
* No simulator moves a CAV: a CAV still in a lane that ends stops with its
  front at the lane end and may change lanes later. A lane change is made
  only where :meth:`diacc.sim.maps.Map.lane_change_allowed` allows it (the rule
  PSAR applies too).

* ``speed_change_mps[i] = NaN``: no command: the CAV drives itself this step
  (car following and lane changes of its vType with the simulator's own
  safety, like the cooperative baseline's CAVs). A CAV of a ``demand``
  scenario drives itself from its entry until the step it first gets a
  command, and while it holds no agent slot (:mod:`diacc.envs.env`).

Entries of HDVs in the command arrays are ignored.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, Protocol, runtime_checkable

import numpy as np

from diacc.errors import DiaccError
from diacc.records import Batched, per_env
from diacc.sim.maps import Map
from diacc.sim.scenario import Scenario
from diacc.sim.settings import BACKENDS, SimConfig
from diacc.sim.state import TrafficState


class BackendError(DiaccError, RuntimeError):
    """A simulator failed (unknown backend, crashed worker...); one-line message."""


@dataclass
class CavCommands(Batched):
    """Commands of E envs for one step, indexed by env and vehicle (HDV entries ignored;
    a :class:`~diacc.records.Batched` record: ``env(e)`` is env ``e``'s batch of one)."""

    lane_change: np.ndarray = per_env("E, V")  # int8 in {-1, 0, +1}, +1 = one lane to the left
    speed_change_mps: np.ndarray = per_env("E, V")  # float64

    @classmethod
    def idle(cls, n_vehicles: int, n_envs: int = 1) -> CavCommands:
        """Commands that keep every CAV in its lane at its speed."""
        shape = (n_envs, n_vehicles)
        return cls(np.zeros(shape, np.int8), np.zeros(shape, np.float64))


@runtime_checkable
class Backend(Protocol):
    """A traffic simulator of one map."""

    name: str
    #: Simulator version recorded with results ("" where diacc's own code simulates).
    version: str
    #: How a vector of environments on this backend steps best (:mod:`diacc.envs.vector`).
    vector_mode: Literal["sync", "batched", "process"]
    road: Map
    sim: SimConfig
    #: E, the envs this backend simulates (1 unless its ``vector_mode`` is "batched").
    n_envs: int

    def reset(self, scenario: Scenario, seed: int, env: int = 0) -> TrafficState:
        """Start env ``env`` anew; its first state, a batch of one."""
        ...

    def step(self, commands: CavCommands) -> TrafficState:
        """Advance every env one decision step with (E, V) commands; the (E, V) state."""
        ...

    def close(self) -> None: ...


#: Backend name -> a function that imports and returns its class. The package
#: :mod:`diacc.sim.backends` fills it (its ``__init__`` runs before this module is
#: used), so this protocol module never imports an implementation, and a
#: simulator (highway-env, libsumo) is loaded only when its backend is asked for.
_LOADERS: dict[str, Callable[[], type[Backend]]] = {}


def register_backend(name: str, loader: Callable[[], type[Backend]]) -> None:
    """Make backend ``name`` (one of :data:`diacc.sim.settings.BACKENDS`) buildable by name."""
    if name not in BACKENDS:
        raise BackendError(f"backend {name!r} is not in diacc.sim.settings.BACKENDS")
    _LOADERS[name] = loader


def backend_class(name: str) -> type[Backend]:
    """The class of backend ``name`` (``"highway"`` or ``"sumo"``), imported only when asked."""
    loader = _LOADERS.get(name)
    if loader is None:
        raise BackendError(f"unknown backend {name!r}; choose one of {', '.join(BACKENDS)}")
    return loader()


def make_backend(name: str, road: Map, sim: SimConfig | None = None) -> Backend:
    """Build a backend by name; ``sim`` (default :class:`SimConfig`) says how, CAV mode included."""
    return backend_class(name)(road, sim or SimConfig())
