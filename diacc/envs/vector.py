"""Many environments stepped as one: in-process or in worker processes.

Every flavour adapts the one step function of :mod:`diacc.envs.batch`
(:class:`~diacc.envs.batch.EnvBatch`, one per map) and adds what the trainer
needs around it (:class:`VectorEnv`): automatic reset with per-episode seeds
derived from the run seed, the final observations of each finished episode
(to bootstrap truncated episodes), episode metrics, and recovery from a
crashed simulator. A step reports the team reward R (``VectorStep.team``) at
the softmin temperature the envs are given (``tau``; the trainer sets it
before each rollout from the schedule, :func:`~diacc.envs.reward.temperature`),
beside the terms R is made of. What a learner uses of them is
:class:`TrainingEnvs`.

* :class:`SyncVectorEnv`: every env on its own simulator, stepped one after
  another in this process (any backend).
* :class:`BatchedVectorEnv` (``highway`` only, its default): each map's envs
  are rows of one batched simulator
  (:meth:`~diacc.sim.backends.highway.backend.HighwayBackend.step`), with
  the same results per env as E simulators (``tests/test_vector.py``). Pipes
  would cost more than they save here.
* :class:`~diacc.envs.vector_process.ProcessVectorEnv` splits the environments into one group per
  worker process (``spawn`` start method; each SUMO environment still runs
  libsumo in a worker of its own), so groups step in parallel; ``highway``
  groups of more than one env are batched. ``vector = "auto"`` takes it when
  the learner is on a GPU (:func:`auto_vector_mode`). A worker that
  dies is restarted and logged when it is found dead: stepping (the episodes
  of its group are cut: ``truncated`` with zero reward terms, bootstrapped
  from the last state before the crash, and counted in ``restarts``) or
  resetting (e.g. after dying idle while the trainer updated: the new worker
  resets with the same seeds). A worker that keeps dying (:data:`MAX_RESTARTS`
  in a row) ends the run with a one-line error. A simulator that fails inside
  a step (:class:`~diacc.sim.backends.base.BackendError`) cuts its env's
  episode the same way.

A run may train on several maps (``TrainConfig.extra_maps``): the environments
are split into contiguous blocks, one per map (:func:`maps_of_envs`), each
block one batch (a batch shares one road). Observations have one layout for
every map, so the trainer sees E environments as before. A training mix
(``TrainConfig.mix``) goes further: each block's *cell* (map, scenario, driver
preset; :class:`~diacc.envs.mix.Cell`) is drawn anew between updates
(:meth:`VectorEnv.set_cells`), and every batch's agent slots are padded to the
most any cell has (slots that never hold a CAV), so that the learner sees one C.
"""

from __future__ import annotations

import itertools
import os
from typing import Protocol, TypeVar

import numpy as np

from diacc.config import EnvConfig, resolve_road
from diacc.envs.batch import EnvBatch, Simulators
from diacc.envs.metrics import EpisodeRecorder
from diacc.envs.mix import Cell
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.step import VectorStep, joined, score
from diacc.envs.vector_process import ProcessVectorEnv
from diacc.runlog import log
from diacc.sim.backends.base import backend_class, make_backend

Padded = TypeVar("Padded", ActorObs, VectorStep)


class TrainingEnvs(Protocol):
    """What a learner uses of the E environments it trains on (every vector env here).

    A protocol, so that the learner (:mod:`diacc.learn.ppo`) depends on these
    members alone, not on how the envs are stepped (in-process, batched, workers).
    """

    n_envs: int  # E
    n_cavs: int  # C agent slots per env
    #: Softmin temperature of the team reward of the next steps: the learner sets it
    #: from its schedule (:func:`~diacc.envs.reward.temperature`); the envs count nothing.
    tau: float

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]: ...

    def step(self, actions: np.ndarray) -> VectorStep: ...  # actions (E, C)

    #: The cell of each env from the next reset on (a training mix's draw; diacc.envs.mix).
    def set_cells(self, env_cells: list[Cell]) -> None: ...

    def close(self) -> None: ...


def maps_of_envs(maps: tuple[str, ...], n_envs: int) -> list[str]:
    """The map of each of ``n_envs`` environments: one near-equal share per entry of ``maps``.

    A map listed k times gets k shares (``("train-50", "train-50", "train-25")`` puts
    two thirds of the environments on ``train-50``). Each map's environments form one
    contiguous block, in order of first appearance, so that a batched group's
    environments are next to each other and the groups' steps concatenate in
    environment order.
    """
    if len(maps) > n_envs:
        raise ValueError(f"{len(maps)} maps need at least as many envs, got {n_envs}")
    shares = np.array_split(np.arange(n_envs), len(maps))  # near-equal, one per entry
    counts = dict.fromkeys(maps, 0)
    for road_map, share in zip(maps, shares, strict=True):
        counts[road_map] += len(share)
    return [road_map for road_map, count in counts.items() for _ in range(count)]


def episode_seed(run_seed: int, env_index: int, episode: int) -> int:
    """Independent, reproducible seed for one episode of one environment."""
    # 31 bits: SUMO's --seed takes a signed 32-bit integer.
    return int(np.random.SeedSequence([run_seed, env_index, episode]).generate_state(1)[0] >> 1)


class VectorEnv:
    """E environments: one :class:`~diacc.envs.batch.EnvBatch` per map, with automatic
    reset, per-episode seeds (:func:`episode_seed`), episode metrics and recovery from
    a crashed simulator (the episode is cut: :func:`~diacc.envs.step.cut_steps`).

    :attr:`batched`: each map's envs are rows of one batched simulator (``highway``;
    a training mix's SUMO block has one simulator per env);
    otherwise every env has its own simulator, stepped one after another. Either
    way PSAR, observations and rewards run once per step for the whole batch.
    ``env_indices``: the run's envs this object holds (their seeds; all of
    ``range(n_envs)`` by default; a worker process holds a group).
    ``env_maps``: the map of each of the run's envs (``config.map`` for all by
    default; :func:`maps_of_envs`).
    """

    #: One batched simulator per map (else one simulator per env).
    batched = False

    def __init__(
        self,
        config: EnvConfig,
        n_envs: int,
        run_seed: int,
        env_indices: list[int] | None = None,
        env_maps: list[str] | None = None,
        env_cells: list[Cell] | None = None,
        n_slots: int | None = None,
    ) -> None:
        self.config, self.run_seed = config, run_seed
        self.tau = config.reward.tau_init  # the team reward's temperature (TrainingEnvs)
        self.env_index = list(range(n_envs)) if env_indices is None else list(env_indices)
        self.n_envs = len(self.env_index)
        #: C: every batch's slots are padded to it (a training mix: its cells' most)
        self.n_cavs = config.scenario.n_slots if n_slots is None else n_slots
        #: Each batch with the positions (in this object) of the envs it holds.
        self.groups: list[tuple[EnvBatch, np.ndarray]] = []
        self.cells: list[Cell] = []  # each batch's
        self.recorders: list[EpisodeRecorder] = []  # each batch's episode metrics
        if env_cells is None:
            if env_maps is not None:
                runs = [m for m, _ in itertools.groupby(env_maps[e] for e in self.env_index)]
                if len(runs) != len(set(runs)):
                    raise ValueError("each map's envs must be one contiguous block (maps_of_envs)")
            by_env = env_maps or [config.map] * (max(self.env_index, default=-1) + 1)
            env_cells = [Cell.of(config, road_map) for road_map in by_env]
        self.set_cells(env_cells)
        self.episode = [0] * self.n_envs  # next episode (seed) of each env
        self._critic: list[CriticState] = []  # each group's latest critic states (crashes)

    def set_cells(self, env_cells: list[Cell]) -> None:
        """Make each env train on its cell (``env_cells``: one per env of the run).

        The envs of one cell next to each other are one batch. A batch whose envs and
        cell are unchanged is kept, the others are closed and built anew (on SUMO their
        simulators restart). Takes effect at the next :meth:`reset`.
        """
        cells = [env_cells[e] for e in self.env_index]
        old = {
            (cell, tuple(members)): g
            for g, (cell, (_, members)) in enumerate(zip(self.cells, self.groups, strict=True))
        }
        groups, recorders, start = [], [], 0
        runs = [(cell, len(list(run))) for cell, run in itertools.groupby(cells)]
        for cell, size in runs:
            members = np.arange(start, start + size)
            start += size
            kept = old.pop((cell, tuple(members)), None)
            if kept is not None:
                groups.append(self.groups[kept])
                recorders.append(self.recorders[kept])
                continue
            cfg = cell.env_config(self.config)
            batch = EnvBatch(cfg, self._simulators(cfg, size))
            if batch.n_cavs > self.n_cavs:
                raise ValueError(
                    f"{cell.label}: {batch.n_cavs} agent slots, more than {self.n_cavs}"
                )
            groups.append((batch, members))
            recorders.append(EpisodeRecorder(batch.road, cfg.events, cfg.scenario.warmup_s, size))
        for g in old.values():
            self.groups[g][0].close()
        self.groups, self.recorders = groups, recorders
        self.cells = [cell for cell, _ in runs]

    def _simulators(self, cfg: EnvConfig, n_envs: int) -> Simulators:
        """The simulations of ``n_envs`` envs of ``cfg``: one batched, or one each."""
        road = resolve_road(cfg)
        cls = backend_class(cfg.backend)
        if self.batched and cls.vector_mode == "batched":
            return Simulators([cls(road, cfg.sim, n_envs=n_envs)])
        if self.batched and cfg.backend == self.config.backend:
            raise ValueError(f"vector mode batched needs the highway backend, not {cfg.backend}")
        # else one each: a training mix's block on a backend that does not batch (SUMO)
        return Simulators([make_backend(cfg.backend, road, cfg.sim) for _ in range(n_envs)])

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Reset every environment (optionally restarting their episode counters)."""
        if first_episode is not None:
            self.episode = [first_episode] * self.n_envs
        pairs = []
        for g, (batch, members) in enumerate(self.groups):
            rows = np.arange(len(members))
            self._start(g, batch, members, rows)
            actor, critic = batch.observe()
            pairs.append((self._padded(batch, actor), critic))
        self._critic = [critic for _, critic in pairs]
        return ActorObs.concat([a for a, _ in pairs]), CriticState.concat([c for _, c in pairs])

    def _start(self, g: int, batch: EnvBatch, members: np.ndarray, rows: np.ndarray) -> None:
        """New episodes in rows ``rows`` of batch ``g`` (positions ``members[rows]``)."""
        seeds = []
        for pos in members[rows]:
            seeds.append(episode_seed(self.run_seed, self.env_index[pos], self.episode[pos]))
            self.episode[pos] += 1
        batch.reset(rows, seeds)
        restarted = np.zeros(len(members), bool)
        restarted[rows] = True
        self.recorders[g].start(rows)
        self.recorders[g].record(batch.state.traffic, rows=restarted)

    def step(self, actions: np.ndarray) -> VectorStep:  # actions (E, C)
        return score(self.step_terms(actions), self.tau, self.config.reward)

    def step_terms(self, actions: np.ndarray) -> VectorStep:
        """:meth:`step` without the team reward (a worker's part: its parent scores)."""
        parts, start = [], 0
        for g, (batch, members) in enumerate(self.groups):
            own = actions[start : start + len(members), : batch.n_cavs]  # (E_g, C_g)
            parts.append(self._padded(batch, self._step_group(g, batch, members, own)))
            start += len(members)
        return joined(parts)

    def _padded(self, batch: EnvBatch, record: Padded) -> Padded:
        """``record`` of ``batch`` with its agent slots padded to this vector env's C by
        slots that never hold a CAV (not alive, zero, every action allowed), so that its
        rows join the others' and add nothing to a loss, an advantage or the team reward
        (a training mix: cells with fewer CAVs than the most; the record itself else)."""
        if batch.n_cavs == self.n_cavs:
            return record
        return record.padded("C", self.n_cavs)

    def _step_group(
        self, g: int, batch: EnvBatch, members: np.ndarray, actions: np.ndarray
    ) -> VectorStep:
        """One step of one batch: record every env's state, end and restart episodes."""
        before = self._critic[g]  # the states a crashed simulator last reached
        out = batch.step(actions)
        ended, crashed = out.terminated | out.truncated, out.crashed
        finals: list[CriticState | None] = [None] * len(members)
        final_actors: list[ActorObs | None] = [None] * len(members)
        episodes: list[dict | None] = [None] * len(members)
        recorder = self.recorders[g]
        recorder.record(out.state, psar=out.psar, critical=out.critical, rows=~crashed)
        for row in np.flatnonzero(crashed).tolist():
            finals[row] = before.unbatched(row)
            log.warning("env %d: %s; its episode is cut", members[row], batch.sims.errors[row])
        for row in np.flatnonzero(ended & ~crashed).tolist():
            finals[row] = out.critic_state.unbatched(row, copy=True)
            final_actors[row] = out.actor_obs.unbatched(row, copy=True)
            episodes[row] = {
                "length": int(batch.state.steps[row]),
                "collision": float(batch.state.wrecked[row].any()),  # anywhere in it
                **recorder.summary(row).as_dict(),
            }
        actor, critic = out.actor_obs, out.critic_state
        restart = np.flatnonzero(ended | crashed)
        if len(restart):
            self._start(g, batch, members, restart)
            new_actor, new_critic = batch.observe(restart)
            actor.set_rows(restart, new_actor)
            critic.set_rows(restart, new_critic)
        self._critic[g] = critic
        kept = ~crashed
        # nothing of a crashed simulator's step happened: no reward nor PSAR outcome there
        done = out if kept.all() else out.where_rows(kept)
        return VectorStep(
            actor_obs=actor,
            critic_state=critic,
            terms=done.terms,
            refined_action=done.refined_action,
            psar_rule=done.psar_rule,
            psar_rule_mask=done.psar_rule_mask,
            slot_start=batch.state.slot_start & kept[:, None],
            terminated=out.terminated & kept,
            truncated=out.truncated | crashed,
            crashed=crashed,
            team=None,
            final_critic_state=finals,
            final_actor_obs=final_actors,
            episode_metrics=episodes,
        )

    def close(self) -> None:
        for batch, _ in self.groups:
            batch.close()


class SyncVectorEnv(VectorEnv):
    """Every env on its own simulator, stepped one after another in this process (any backend)."""

    batched = False


class BatchedVectorEnv(VectorEnv):
    """Each map's envs as rows of one batched ``highway`` simulator (its default vector mode)."""

    batched = True


def make_vector_env(
    config: EnvConfig,
    n_envs: int,
    run_seed: int,
    mode: str = "auto",
    extra_maps: tuple[str, ...] = (),
    learner_device: str = "cpu",
    env_cells: list[Cell] | None = None,
    n_slots: int | None = None,
) -> TrainingEnvs:
    """``mode``: ``sync``, ``batched``, ``process`` or ``auto`` (:func:`auto_vector_mode`).

    ``process`` starts one worker per CPU core (at most one per env); on
    ``highway`` each worker steps its group as one batch when some group holds
    more than one env (the same results, :class:`BatchedVectorEnv`).
    ``extra_maps``: maps beside ``config.map`` that the environments are split
    over (:func:`maps_of_envs`). ``learner_device``: where the PPO update runs
    (``cpu``, ``cuda``), which ``auto`` depends on. ``env_cells``: each env's cell
    (a training mix's first draw, :mod:`diacc.envs.mix`) instead of ``config``'s and
    ``extra_maps``; ``n_slots``: the agent slots C every env is padded to (default
    ``config.scenario``'s).
    """
    env_maps = maps_of_envs((config.map, *extra_maps), n_envs) if extra_maps else None
    kwargs = {"env_maps": env_maps, "env_cells": env_cells, "n_slots": n_slots}
    if mode == "auto":
        mode = auto_vector_mode(config.backend, n_envs, learner_device)
    if mode == "sync":
        return SyncVectorEnv(config, n_envs, run_seed, **kwargs)
    if mode == "batched":
        return BatchedVectorEnv(config, n_envs, run_seed, **kwargs)
    if mode == "process":
        workers = min(n_envs, os.cpu_count() or 1)
        batches = backend_class(config.backend).vector_mode == "batched" and n_envs > workers
        group = BatchedVectorEnv if batches else SyncVectorEnv
        return ProcessVectorEnv(group, config, n_envs, run_seed, workers, **kwargs)
    raise ValueError(f"unknown vector mode {mode!r}; choose sync, batched, process or auto")


def auto_vector_mode(backend: str, n_envs: int, learner_device: str = "cpu") -> str:
    """What ``vector = "auto"`` means: the backend's ``vector_mode``, except in two cases.

    A single environment steps on its own (``sync``): a batch of one gives the
    same results but pays the batching (``diacc bench --env-batch``; figures in
    docs/benchmarks, "env stepping per core"). With the learner on a GPU
    (``learner_device`` ``cuda``) the CPU cores have nothing to do but step the
    envs and act, so the envs are spread over one worker process per core
    (``process``), as soon as there are two envs and two cores.
    """
    if learner_device == "cuda" and n_envs > 1 and (os.cpu_count() or 1) > 1:
        return "process"
    mode = backend_class(backend).vector_mode
    if mode == "batched" and n_envs == 1:
        return "sync"
    return mode
