"""Many environments stepped as one: in-process or in worker processes.

Every flavour adapts the one step function of :mod:`diacc.envs.batch`
(:class:`~diacc.envs.batch.EnvBatch`, one per map) and adds what the trainer
needs around it (:class:`VectorEnv`): automatic reset with per-episode seeds
derived from the run seed, the final observations of each finished episode
(to bootstrap truncated episodes), episode metrics, and recovery from a
crashed simulator. A step reports the reward's terms that need no temperature
(each CAV's ego reward, the global, completion and delay terms,
:func:`~diacc.envs.reward.reward_terms`), not a team reward: the softmin
temperature anneals over training and is the trainer's, which makes the team
reward of them (:func:`~diacc.envs.reward.team_reward`,
:func:`diacc.learn.mappo.collect_rollout`), and the episodes' returns.

* :class:`SyncVectorEnv`: every env on its own simulator, stepped one after
  another in this process (any backend).
* :class:`BatchedVectorEnv` (``highway`` only, its default): each map's envs
  are rows of one batched simulator
  (:meth:`~diacc.sim.backends.highway.backend.HighwayBackend.step`), with
  the same results per env as E simulators (``tests/test_vector.py``). Pipes
  would cost more than they save here.
* :class:`ProcessVectorEnv` splits the environments into one group per
  worker process (``spawn`` start method; each SUMO environment still runs
  libsumo in a worker of its own), so groups step in parallel. A worker that
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
every map, so the trainer sees E environments as before.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from dataclasses import dataclass, fields, replace

import numpy as np

from diacc.config import EnvConfig, preset_road
from diacc.envs.batch import EnvBatch, Simulators
from diacc.envs.metrics import EpisodeRecorder
from diacc.envs.observation import ActorObs, CriticState, concat, unstack
from diacc.runlog import join_parent_log, log
from diacc.sim.backends.base import backend_class, make_backend
from diacc.sim.maps import load_map
from diacc.threads import worker_environment

#: Restarts of one worker in a row (within one call) before the vector env gives up.
MAX_RESTARTS = 3


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


@dataclass
class VectorStep:
    """One step of E environments, after the automatic resets.

    The team reward of the step is :func:`~diacc.envs.reward.team_reward` of
    ``ego``, ``alive``, ``global_reward``, ``completion`` and ``delay`` at the
    trainer's temperature.
    """

    actor_obs: ActorObs  # fields (E, C, ...)
    critic_state: CriticState  # fields (E, ...)
    ego: np.ndarray  # (E, C) ego reward r_e of each CAV slot
    global_reward: np.ndarray  # (E,) r_g
    completion: np.ndarray  # (E,) r_done
    delay: np.ndarray  # (E,) delay term before its weight
    terminated: np.ndarray  # (E,) bool
    truncated: np.ndarray  # (E,) bool
    alive: np.ndarray  # (E, C) bool: CAV on the road after the step (the reward's mask)
    refined_action: np.ndarray  # (E, C)
    psar_rule_mask: np.ndarray  # (E, C)
    final_critic_state: list[CriticState | None]  # (E,)
    final_actor_obs: list[ActorObs | None]  # (E,) (None also after a simulator crash)
    episodes: dict[int, dict]  # env index -> metrics of the episode that ended there this step
    reward_terms: dict[str, np.ndarray]  # logged parts of the reward, (E',) over ~restarted envs
    restarted: np.ndarray  # (E,) bool: the simulator crashed, the step was cut (no reward terms)
    restarts: int
    slot_start: np.ndarray  # (E, C) bool: a new CAV took the slot; its next action starts afresh


def concat_steps(parts: list[VectorStep]) -> VectorStep:
    """The steps of groups of envs as one, in group order (env indices follow on)."""
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [len(p.terminated) for p in parts])
    terms = [p.reward_terms for p in parts if p.reward_terms]
    return VectorStep(
        actor_obs=concat([p.actor_obs for p in parts]),
        critic_state=concat([p.critic_state for p in parts]),
        **{name: np.concatenate([getattr(p, name) for p in parts]) for name in _ARRAY_FIELDS},
        final_critic_state=[c for p in parts for c in p.final_critic_state],
        final_actor_obs=[a for p in parts for a in p.final_actor_obs],
        episodes={
            int(o) + e: m
            for p, o in zip(parts, offsets, strict=False)
            for e, m in p.episodes.items()
        },
        reward_terms={
            key: np.concatenate([t[key] for t in terms]) for key in (terms[0] if terms else {})
        },
        restarts=sum(p.restarts for p in parts),
    )


#: VectorStep's fields that are plain (E, ...) arrays.
_ARRAY_FIELDS = (
    "ego",
    "global_reward",
    "completion",
    "delay",
    "terminated",
    "truncated",
    "alive",
    "refined_action",
    "psar_rule_mask",
    "restarted",
    "slot_start",
)


def cut_steps(
    actor: ActorObs, critic: CriticState, finals: list[CriticState | None], n_cavs: int
) -> VectorStep:
    """The step reported for envs whose simulator crashed: episode cut, no reward, fresh start.

    ``actor``/``critic``: the envs' first observations of their new episodes;
    ``finals``: each env's last state before the crash. No CAV is on the road and
    every reward term is 0, so the team reward is 0 at any temperature. A crash is
    not the episode's end but ours, so it is a *truncation*: the trainer
    bootstraps from the last state the simulator reached (a termination would
    teach the critic that a crash is worth 0).
    """
    n = len(finals)
    return VectorStep(
        actor_obs=actor,
        critic_state=critic,
        ego=np.zeros((n, n_cavs)),
        global_reward=np.zeros(n),
        completion=np.zeros(n),
        delay=np.zeros(n),
        terminated=np.zeros(n, bool),
        truncated=np.ones(n, bool),
        alive=np.zeros((n, n_cavs), bool),
        refined_action=np.zeros((n, n_cavs), np.int64),
        psar_rule_mask=np.zeros((n, n_cavs), np.int8),
        final_critic_state=list(finals),
        final_actor_obs=[None] * n,
        episodes={},
        reward_terms={},
        restarted=np.ones(n, bool),
        restarts=n,
        slot_start=np.zeros((n, n_cavs), bool),
    )


class VectorEnv:
    """E environments: one :class:`~diacc.envs.batch.EnvBatch` per map, with automatic
    reset, per-episode seeds (:func:`episode_seed`), episode metrics and recovery from
    a crashed simulator (the episode is cut: :func:`cut_steps`).

    :attr:`batched`: each map's envs are rows of one batched simulator (``highway``);
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
    ) -> None:
        self.config, self.run_seed = config, run_seed
        self.env_index = list(range(n_envs)) if env_indices is None else list(env_indices)
        maps = [config.map if env_maps is None else env_maps[e] for e in self.env_index]
        self.n_envs, self.n_cavs = len(self.env_index), config.scenario.n_slots
        #: Each batch with the positions (in this object) of the envs it holds.
        self.groups: list[tuple[EnvBatch, np.ndarray]] = []
        for road_map in dict.fromkeys(maps):  # in order of first appearance
            members = np.flatnonzero([m == road_map for m in maps])
            cfg = replace(config, map=road_map)
            road = preset_road(load_map(road_map), cfg.sim.style_preset)
            if self.batched:
                cls = backend_class(cfg.backend)
                if cls.vector_mode != "batched":
                    raise ValueError(
                        f"vector mode batched needs the highway backend, not {cfg.backend}"
                    )
                backends = [cls(road, cfg.sim, n_envs=len(members))]
            else:
                backends = [make_backend(cfg.backend, road, cfg.sim) for _ in members]
            self.groups.append((EnvBatch(cfg, Simulators(backends)), members))
        order = np.concatenate([members for _, members in self.groups])
        if not np.array_equal(order, np.arange(self.n_envs)):
            raise ValueError("each map's envs must be one contiguous block (maps_of_envs)")
        self.episode = [0] * self.n_envs  # next episode (seed) of each env
        #: each batch's episode metrics, its envs side by side
        self.recorders = [
            EpisodeRecorder(batch.road, config.events, config.scenario.warmup_s, len(members))
            for batch, members in self.groups
        ]
        self._critic: list[CriticState] = []  # each group's latest critic states (crashes)

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Reset every environment (optionally restarting their episode counters)."""
        if first_episode is not None:
            self.episode = [first_episode] * self.n_envs
        pairs = []
        for g, (batch, members) in enumerate(self.groups):
            rows = np.arange(len(members))
            self._start(g, batch, members, rows)
            pairs.append(batch.observe())
        self._critic = [critic for _, critic in pairs]
        return concat([a for a, _ in pairs]), concat([c for _, c in pairs])

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
        parts, start = [], 0
        for g, (batch, members) in enumerate(self.groups):
            parts.append(self._step_group(g, batch, members, actions[start : start + len(members)]))
            start += len(members)
        return concat_steps(parts)

    def _step_group(
        self, g: int, batch: EnvBatch, members: np.ndarray, actions: np.ndarray
    ) -> VectorStep:
        """One step of one batch: record every env's state, end and restart episodes."""
        before = self._critic[g]  # the states a crashed simulator last reached
        out = batch.step(actions)
        ended, crashed = out.terminated | out.truncated, out.crashed
        finals: list[CriticState | None] = [None] * len(members)
        final_actors: list[ActorObs | None] = [None] * len(members)
        episodes = {}
        recorder = self.recorders[g]
        recorder.record(out.state, psar=out.decision.psar, critical=out.critical, rows=~crashed)
        for row in np.flatnonzero(crashed).tolist():
            finals[row] = unstack(before, row)
        for row in np.flatnonzero(ended & ~crashed).tolist():
            finals[row] = unstack(out.critic_state, row, copy=True)
            final_actors[row] = unstack(out.actor_obs, row, copy=True)
            episodes[row] = {
                "length": int(batch.state.steps[row]),
                "collision": float((out.state.collisions[:, 0] == row).any()),
                **recorder.summary(row).as_dict(),
            }
        actor, critic = out.actor_obs, out.critic_state
        restart = np.flatnonzero(ended | crashed)
        if len(restart):
            self._start(g, batch, members, restart)
            new_actor, new_critic = batch.observe(restart)
            for container, new in ((actor, new_actor), (critic, new_critic)):
                for f in fields(container):
                    getattr(container, f.name)[restart] = getattr(new, f.name)
        self._critic[g] = critic
        kept = ~crashed

        def of_kept(values: np.ndarray, fill: float | int = 0) -> np.ndarray:
            """``values`` of the envs whose step happened, ``fill`` in the others."""
            if not crashed.any():
                return values
            return np.where(kept.reshape((-1,) + (1,) * (values.ndim - 1)), values, fill)

        return VectorStep(
            actor_obs=actor,
            critic_state=critic,
            ego=of_kept(out.terms.ego, 0.0),
            global_reward=of_kept(out.terms.global_reward, 0.0),
            completion=of_kept(out.terms.completion, 0.0),
            delay=of_kept(out.terms.delay, 0.0),
            terminated=out.terminated & kept,
            truncated=out.truncated | crashed,
            alive=out.terms.alive & kept[:, None],
            refined_action=of_kept(out.decision.refined),
            psar_rule_mask=of_kept(out.decision.rule_mask).astype(np.int8),
            final_critic_state=finals,
            final_actor_obs=final_actors,
            episodes=episodes,
            reward_terms=out.logged_terms(np.flatnonzero(kept)),  # of the envs whose step happened
            restarted=crashed,
            restarts=int(crashed.sum()),
            slot_start=batch.state.slot_start & kept[:, None],
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


def _worker(
    conn,
    config: EnvConfig,
    run_seed: int,
    env_indices: list[int],
    episode: int,
    env_maps: list[str] | None = None,
) -> None:
    # Ctrl-C is for the trainer, which stops at the next update boundary; the
    # worker (and the SUMO processes it starts, which inherit this) carries on.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    join_parent_log()  # e.g. a SUMO worker restarted at reset
    group = SyncVectorEnv(config, 0, run_seed, env_indices, env_maps)
    group.episode = [episode] * group.n_envs
    try:
        while True:
            command, payload = conn.recv()
            if command == "step":
                conn.send(group.step(payload))
            elif command == "reset":
                conn.send(group.reset(payload))
            elif command == "close":
                break
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        group.close()
        conn.close()


class ProcessVectorEnv:
    """E environments in W worker processes (a group of about E / W each), stepped in parallel.

    W defaults to one worker per CPU core (at most E): more workers than cores
    only add switching, fewer leave cores idle.
    """

    def __init__(
        self,
        config: EnvConfig,
        n_envs: int,
        run_seed: int,
        n_workers: int | None = None,
        env_maps: list[str] | None = None,
    ) -> None:
        self.config, self.run_seed, self.env_maps = config, run_seed, env_maps
        self.n_envs, self.n_cavs = n_envs, config.scenario.n_slots
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
            args=(child, self.config, self.run_seed, self.groups[w], episode, self.env_maps),
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
        actor, critic = concat([a for a, _ in pairs]), concat([c for _, c in pairs])
        self._last_critic = [unstack(critic, e, copy=True) for e in range(self.n_envs)]
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
        out = concat_steps(parts)
        self._last_critic = [unstack(out.critic_state, e, copy=True) for e in range(self.n_envs)]
        return out

    def close(self) -> None:
        for p, w in zip(self.pipes, self.workers, strict=True):
            try:
                p.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
            w.join(timeout=5)
            if w.is_alive():
                w.kill()


def make_vector_env(
    config: EnvConfig,
    n_envs: int,
    run_seed: int,
    mode: str = "auto",
    extra_maps: tuple[str, ...] = (),
):
    """``mode``: ``sync``, ``batched``, ``process`` or ``auto`` (the backend's ``vector_mode``).

    ``auto`` steps a single environment on its own (``sync``): a batch of one
    gives the same results but pays the batching (measured x0.70 env-steps/s,
    ``diacc bench --env-batch``). ``extra_maps``: maps beside ``config.map`` that
    the environments are split over (:func:`maps_of_envs`).
    """
    env_maps = maps_of_envs((config.map, *extra_maps), n_envs) if extra_maps else None
    if mode == "auto":
        mode = backend_class(config.backend).vector_mode
        if mode == "batched" and n_envs == 1:
            mode = "sync"
    if mode == "sync":
        return SyncVectorEnv(config, n_envs, run_seed, env_maps=env_maps)
    if mode == "batched":
        return BatchedVectorEnv(config, n_envs, run_seed, env_maps=env_maps)
    if mode == "process":
        return ProcessVectorEnv(config, n_envs, run_seed, env_maps=env_maps)
    raise ValueError(f"unknown vector mode {mode!r}; choose sync, batched, process or auto")
