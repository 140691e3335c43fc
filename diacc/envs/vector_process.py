"""The vector env in worker processes: groups of environments stepped in parallel.

:class:`ProcessVectorEnv` (:mod:`diacc.envs.vector`, module docstring) splits
the environments into one group per ``spawn``-ed worker process, each group
an object of ``group_class`` (:class:`~diacc.envs.vector.SyncVectorEnv`, which
:func:`~diacc.envs.vector.make_vector_env` passes); a worker that dies is
replaced, logged, and its group's episodes are cut
(:func:`~diacc.envs.step.cut_steps`).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal

import numpy as np

from diacc.config import EnvConfig
from diacc.envs.mix import Cell
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.step import VectorStep, cut_steps, joined, score
from diacc.runlog import join_parent_log, log
from diacc.threads import worker_environment

#: Restarts of one worker in a row (within one call) before the vector env gives up.
MAX_RESTARTS = 3


def _worker(
    conn,
    group_class: type,
    config: EnvConfig,
    run_seed: int,
    env_indices: list[int],
    episode: int,
    env_maps: list[str] | None = None,
    env_cells: list[Cell] | None = None,
    n_slots: int | None = None,
) -> None:
    # Ctrl-C is for the trainer, which stops at the next update boundary; the
    # worker (and the SUMO processes it starts, which inherit this) carries on.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    join_parent_log()  # e.g. a SUMO worker restarted at reset
    group = group_class(config, 0, run_seed, env_indices, env_maps, env_cells, n_slots)
    group.episode = [episode] * group.n_envs
    try:
        while True:
            command, payload = conn.recv()
            if command == "step":
                conn.send(group.step_terms(payload))
            elif command == "reset":
                conn.send(group.reset(payload))
            elif command == "cells":
                group.set_cells(payload)
                conn.send(None)
            elif command == "close":
                break
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        group.close()
        conn.close()


class ProcessVectorEnv:
    """E environments in W worker processes (a group of about E / W each), stepped in parallel.

    ``group_class``: what each worker steps its group with (``SyncVectorEnv``).
    W defaults to one worker per CPU core (at most E): more workers than cores
    only add switching, fewer leave cores idle. The team reward is made here,
    in the parent, at the temperature it is given (``tau``, as
    :class:`~diacc.envs.vector.VectorEnv`'s).
    """

    def __init__(
        self,
        group_class: type,
        config: EnvConfig,
        n_envs: int,
        run_seed: int,
        n_workers: int | None = None,
        env_maps: list[str] | None = None,
        env_cells: list[Cell] | None = None,
        n_slots: int | None = None,
    ) -> None:
        self.group_class = group_class
        self.config, self.run_seed, self.env_maps = config, run_seed, env_maps
        self.env_cells = env_cells  # each env's cell (a training mix), or None
        self.tau = config.reward.tau_init  # the team reward's temperature (TrainingEnvs)
        self.n_envs = n_envs
        self.n_cavs = config.scenario.n_slots if n_slots is None else n_slots
        n_workers = min(n_envs, n_workers or os.cpu_count() or 1)
        self.groups = [g.tolist() for g in np.array_split(np.arange(n_envs), n_workers)]
        self.ctx = mp.get_context("spawn")
        self.restarts = 0
        self._last_critic: list[CriticState | None] = [None] * n_envs  # bootstrap on a crash
        self.workers: list = [None] * n_workers
        self.pipes: list = [None] * n_workers
        for w in range(n_workers):
            self._start(w, episode=0)

    def _start(self, w: int, episode: int) -> None:
        parent, child = self.ctx.Pipe()
        proc = self.ctx.Process(
            target=_worker,
            args=(
                child,
                self.group_class,
                self.config,
                self.run_seed,
                self.groups[w],
                episode,
                self.env_maps,
                self.env_cells,
                self.n_cavs,
            ),
            daemon=True,
        )
        with worker_environment():  # one library thread per worker (diacc.threads)
            proc.start()
        child.close()
        self.workers[w], self.pipes[w] = proc, parent

    def _replace(self, w: int) -> None:
        """Start a new worker in place of dead worker ``w``; logged, and bounded per call."""
        old = self.workers[w]
        old.kill()
        old.join()
        self.restarts += 1
        log.warning(
            "vector env worker %d (envs %s, pid %s) died (exit code %s); started a new one "
            "and cut its episodes",
            w,
            self.groups[w],
            old.pid,
            old.exitcode,
        )
        # Episode numbers keep counting up, so a restarted env never repeats a seed.
        self._start(w, episode=1_000_000 + self.restarts)

    def _call(self, w: int, message: tuple):
        """Send ``message`` to worker ``w`` and return its reply, replacing the worker if dead."""
        for attempt in range(1, MAX_RESTARTS + 2):
            try:
                self.pipes[w].send(message)
                return self.pipes[w].recv()
            except (EOFError, ConnectionError, OSError):
                if attempt > MAX_RESTARTS:
                    raise RuntimeError(
                        f"vector env worker {w} died {attempt} times in a row; giving up"
                    ) from None
                self._replace(w)

    def _restart(self, w: int) -> VectorStep:
        """Replace a dead worker; every episode of its group is cut."""
        self._replace(w)
        finals = [self._last_critic[e] for e in self.groups[w]]
        actor, critic = self._call(w, ("reset", None))
        return cut_steps(actor, critic, finals, self.n_cavs)

    def set_cells(self, env_cells: list[Cell]) -> None:
        """Each env's cell from the next reset on (each worker rebuilds the batches whose
        cell changed; a worker started later starts with them)."""
        self.env_cells = list(env_cells)
        for w in range(len(self.pipes)):
            self._call(w, ("cells", self.env_cells))

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Reset every environment (optionally restarting their episode counters).

        A worker that died meanwhile (e.g. idle during the trainer's update) is
        replaced here, with the same seeds.
        """
        sent = [self._send(w, ("reset", first_episode)) for w in range(len(self.pipes))]
        pairs = []
        for w, ok in enumerate(sent):
            reply = self._receive(w) if ok else None
            if reply is None:  # same seeds on the new worker: the reset is unchanged
                self._replace(w)
                reply = self._call(w, ("reset", first_episode))
            pairs.append(reply)
        actor = ActorObs.concat([a for a, _ in pairs])
        critic = CriticState.concat([c for _, c in pairs])
        self._last_critic = [critic.unbatched(e, copy=True) for e in range(self.n_envs)]
        return actor, critic

    def _send(self, w: int, message: tuple) -> bool:
        try:
            self.pipes[w].send(message)
            return True
        except (ConnectionError, OSError):
            return False

    def _receive(self, w: int):
        try:
            return self.pipes[w].recv()
        except (EOFError, ConnectionError, OSError):
            return None

    def step(self, actions: np.ndarray) -> VectorStep:  # actions (E, C)
        sent = [self._send(w, ("step", actions[group])) for w, group in enumerate(self.groups)]
        parts: list[VectorStep] = []
        for w, ok in enumerate(sent):
            reply = self._receive(w) if ok else None
            parts.append(reply if reply is not None else self._restart(w))
        out = joined(parts)
        self._last_critic = [out.critic_state.unbatched(e, copy=True) for e in range(self.n_envs)]
        return score(out, self.tau, self.config.reward)

    def close(self) -> None:
        for p, w in zip(self.pipes, self.workers, strict=True):
            try:
                p.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
            w.join(timeout=5)
            if w.is_alive():
                w.kill()
