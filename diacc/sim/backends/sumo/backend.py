"""The ``sumo`` backend: libsumo in a worker process, behind the Backend protocol.

libsumo keeps one simulation per process, so each :class:`SumoBackend` starts
its own worker process and talks to it over a socket pair wrapped in a
``multiprocessing.connection.Connection`` (pickled messages; each step in the
compact encoding of :mod:`.wire`). The worker is a
fresh interpreter (``python -m diacc.sim.backends.sumo.worker``), never a fork, so
it is safe after torch or libsumo were imported here. It is started with
``subprocess`` rather than a ``multiprocessing`` ``spawn`` context because
``spawn`` re-runs the caller's main script in the child, which breaks every
user script without an ``if __name__ == "__main__"`` guard; see
:mod:`.worker` for what runs there, :mod:`.net` for the network built from
the map and :mod:`.vtypes` for the vehicle types.

CAV modes (``SimConfig.cav_mode``):

* ``"commanded"`` (default): CAVs follow :class:`CavCommands` (speedMode 0,
  laneChangeMode 0: lane changes only on command; at a lane end the CAV
  stops).
* ``"cooperative"``: the paper's non-learning cooperative baseline: CAVs are
  SUMO CACC vehicles with ``lcCooperative = 1`` and ignore the commands.

Failure handling: if the worker dies, the call raises :class:`BackendError`
naming the map and seed, and the next :meth:`reset` starts a fresh worker.
Workers are closed by :meth:`close`, by garbage collection and at interpreter
exit (a ``weakref.finalize``); a worker whose parent vanished without closing
(SIGKILL) reads end-of-file on its connection and exits, so none outlives
its owner.
"""

from __future__ import annotations

import os
import pickle
import socket
import subprocess
import sys
import weakref
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from diacc.fileio import atomic_write
from diacc.runlog import log
from diacc.sim.backends.base import BackendError, CavCommands
from diacc.sim.backends.sumo import wire
from diacc.sim.backends.sumo.net import build_network
from diacc.sim.backends.sumo.vtypes import vtypes_key, vtypes_xml
from diacc.sim.backends.sumo.worker import WorkerSpec
from diacc.sim.maps import Map
from diacc.sim.scenario import Scenario, draw_population
from diacc.sim.settings import SimConfig
from diacc.sim.state import TrafficState
from diacc.threads import worker_env

#: Folder holding the ``diacc`` package, put on the worker's PYTHONPATH.
_PACKAGE_ROOT = str(Path(__file__).resolve().parents[4])
#: Seconds to wait for a worker to start SUMO (spawning an interpreter and
#: importing libsumo takes about a second on a quiet machine).
START_TIMEOUT_S = 120.0
#: Seconds a single reset/step may take before the worker is declared hung.
REQUEST_TIMEOUT_S = 300.0


class SumoBackend:
    """SUMO (libsumo) simulation of one map; see the module docstring."""

    name = "sumo"
    #: libsumo holds one simulation per process: environments step in worker processes.
    vector_mode = "process"
    #: One simulation: every state is a batch of one.
    n_envs = 1

    def __init__(self, road: Map, sim: SimConfig) -> None:
        self.road = road
        self.sim = sim
        net_path, route_path = build_network(road)
        vtypes_path = net_path.parent / f"vtypes-{vtypes_key(sim)}.add.xml"  # the usable cache
        vtypes = vtypes_xml(sim)
        if not vtypes_path.exists() or vtypes_path.read_text(errors="replace") != vtypes:
            atomic_write(vtypes_path, vtypes)
        self._spec = WorkerSpec(road, sim, net_path, route_path, vtypes_path)
        self._proc: subprocess.Popen | None = None
        self._conn = None
        self._finalizer: weakref.finalize | None = None
        self._seed: int | None = None
        self._state: TrafficState | None = None
        self._pending = False
        self.version = ""  # "SUMO 1.x", once the worker has started
        self._start_worker()

    # ---- worker lifecycle ---------------------------------------------------
    def _start_worker(self) -> None:
        parent_sock, child_sock = socket.socketpair()
        child_fd = child_sock.fileno()
        env = worker_env()  # one library thread (diacc.threads)
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (_PACKAGE_ROOT, env.get("PYTHONPATH", "")) if p
        )
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "diacc.sim.backends.sumo.worker", str(child_fd)],
                pass_fds=(child_fd,),
                stdin=subprocess.DEVNULL,
                env=env,
            )
        except OSError as exc:
            parent_sock.close()
            raise BackendError(
                f"cannot start a SUMO worker for map {self.road.name!r}: {exc}"
            ) from None
        finally:
            child_sock.close()
        conn = Connection(parent_sock.detach())
        self._proc, self._conn = proc, conn
        self._finalizer = weakref.finalize(self, _stop_worker, proc, conn)
        self._send(("spec", self._spec), "starting SUMO")
        self.version = self._receive(START_TIMEOUT_S, "starting SUMO")

    def _worker_alive(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    @property
    def worker_pid(self) -> int | None:
        """Process id of the current worker (None when closed)."""
        return self._proc.pid if self._proc is not None else None

    def _receive(self, timeout_s: float, doing: str):
        """Wait for the worker's reply; a dead or silent worker becomes a BackendError."""
        conn, proc = self._conn, self._proc
        waited = 0.0
        try:
            while not conn.poll(0.2):
                waited += 0.2
                if proc.poll() is not None or waited > timeout_s:
                    raise EOFError
            message = conn.recv_bytes()
        except (EOFError, OSError, BrokenPipeError):
            code = proc.poll()
            self._discard_worker()
            raise BackendError(
                f"SUMO worker died while {doing} (map {self.road.name!r}, seed {self._seed}, "
                f"exit code {code}); the next reset() starts a new worker"
            ) from None
        if wire.is_state_reply(message):
            return wire.decode_state(message)
        status, payload = pickle.loads(message)
        if status != "ok":
            raise BackendError(f"SUMO error while {doing} (map {self.road.name!r}, "
                               f"seed {self._seed}): {payload}")  # fmt: skip
        return payload

    def _discard_worker(self) -> None:
        if self._finalizer is not None:
            self._finalizer()  # stops and reaps the process, closes the pipe
        self._proc, self._conn, self._finalizer = None, None, None
        self._pending = False

    def _send(self, msg: tuple | bytes, doing: str) -> None:
        """Send a pickled request, or a :mod:`.wire` step request as it is."""
        if not self._worker_alive():
            code = self._proc.poll() if self._proc is not None else None
            self._discard_worker()
            raise BackendError(
                f"SUMO worker is not running while {doing} (map {self.road.name!r}, "
                f"seed {self._seed}, exit code {code}); call reset() to start a new worker"
            )
        try:
            if isinstance(msg, bytes):
                self._conn.send_bytes(msg)
            else:
                self._conn.send(msg)
        except (OSError, BrokenPipeError):
            self._discard_worker()
            raise BackendError(
                f"SUMO worker died while {doing} (map {self.road.name!r}, seed {self._seed})"
            ) from None

    # ---- Backend protocol -----------------------------------------------------
    def reset(self, scenario: Scenario, seed: int, env: int = 0) -> TrafficState:
        """Insert ``draw_population(scenario, road, seed)`` at t = 0, SUMO seeded by ``seed``;
        the state as a batch of one (``env`` is 0, the only one)."""
        if env != 0:
            raise BackendError(f"env {env}: a SUMO backend simulates env 0 only")
        population = draw_population(scenario, self.road, seed)
        if self._pending:
            self._receive(REQUEST_TIMEOUT_S, "finishing a step before reset")
            self._pending = False
        if not self._worker_alive():
            if self._proc is not None:  # died while idle: nobody has reported it yet
                log.warning(
                    "SUMO worker (pid %s, map %r) had exited with code %s; starting a new one",
                    self._proc.pid,
                    self.road.name,
                    self._proc.poll(),
                )
            self._discard_worker()
            self._start_worker()
        self._seed = int(seed)
        self._send(("reset", self._seed, population), "resetting")
        self._state = self._receive(REQUEST_TIMEOUT_S, "resetting")
        return self._state

    def step_async(self, commands: CavCommands) -> None:
        """Send one step's commands without waiting (pair with :meth:`step_wait`).

        Lets several backends advance their simulations concurrently.
        """
        if self._state is None:
            raise BackendError(f"step() before reset() on SUMO map {self.road.name!r}")
        if self._pending:
            raise BackendError("step_async() called twice without step_wait()")
        n = self._state.n_vehicles
        lane_change = np.asarray(commands.lane_change)
        speed_change = np.asarray(commands.speed_change_mps, dtype=np.float64)
        if lane_change.shape != (1, n) or speed_change.shape != (1, n):
            raise BackendError(
                f"CavCommands arrays must have shape (1, {n}), got {lane_change.shape} and "
                f"{speed_change.shape}"
            )
        self._send(wire.encode_step_request(lane_change[0], speed_change[0]), "stepping")
        self._pending = True

    def step_wait(self) -> TrafficState:
        """Receive the state of the step sent by :meth:`step_async`."""
        if not self._pending:
            raise BackendError("step_wait() without a pending step_async()")
        self._pending = False
        self._state = self._receive(REQUEST_TIMEOUT_S, "stepping")
        return self._state

    def step(self, commands: CavCommands) -> TrafficState:
        """Apply (1, V) CAV commands (ignored in ``cooperative`` mode) and advance
        ``sim.step_s``; the state as a batch of one."""
        self.step_async(commands)
        return self.step_wait()

    def close(self) -> None:
        """Stop the worker process (idempotent)."""
        self._discard_worker()
        self._state = None

    def __enter__(self) -> SumoBackend:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _stop_worker(proc: subprocess.Popen, conn: Connection) -> None:
    """Ask the worker to close, then make sure it is gone and reaped (no zombie)."""
    try:
        if proc.poll() is None:
            conn.send(("close",))
            proc.wait(timeout=2.0)
    except (OSError, ValueError, subprocess.TimeoutExpired):
        pass
    if proc.poll() is None:
        proc.kill()
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:  # pragma: no cover - a killed process always ends
        pass
    try:
        conn.close()
    except OSError:
        pass
