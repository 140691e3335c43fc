"""Many environments stepped as one batch: in-process or in worker processes.

All flavours run the same :class:`EnvRunner` per environment, which adds
what the trainer needs around :class:`~diacc.envs.env.BottleneckEnv`: automatic
reset with per-episode seeds derived from the run seed, the final critic
state of each finished episode (to bootstrap truncated episodes), episode
metrics, and recovery from a crashed simulator. A step reports the reward's
terms that need no temperature (each CAV's ego reward, the global, completion
and delay terms, :func:`~diacc.envs.reward.reward_terms`), not a team reward:
the softmin temperature anneals over training and is the trainer's, which
makes the team reward of them (:func:`~diacc.envs.reward.team_reward`,
:func:`diacc.learn.mappo.collect_rollout`), and the episodes' returns.

* :class:`SyncVectorEnv` steps environments one after another in this
  process.
* :class:`BatchedVectorEnv` (``highway`` only, its default) is the same with
  one batched simulator for all environments: PSAR, observations and rewards
  are still per environment, but the simulation of all E envs is one
  :meth:`~diacc.sim.backends.highway.backend.HighwayBackend.step_batch` call,
  with the same results per env as E simulators
  (``tests/test_vector.py``). Pipes would cost more than they save here.
* :class:`ProcessVectorEnv` splits the environments into one group per
  worker process (``spawn`` start method; each SUMO environment still runs
  libsumo in a worker of its own), so groups step in parallel. A worker that
  dies is restarted and logged when it is found dead: stepping (the episodes
  of its group are cut: ``truncated`` with zero reward terms, bootstrapped
  from the last state before the crash, and counted in ``restarts``) or
  resetting (e.g. after dying idle while the trainer updated: the new worker
  resets with the same seeds). A worker that keeps dying (:data:`MAX_RESTARTS`
  in a row) ends the run with a one-line error.

A run may train on several maps (``TrainConfig.extra_maps``): the environments
are split into contiguous blocks, one per map (:func:`maps_of_envs`); a batched
run steps one :class:`BatchedVectorEnv` per map (a batch shares one road) inside
a :class:`MapGroupsVectorEnv`. Observations have one layout for every map, so
the trainer sees E environments as before.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from dataclasses import dataclass, replace

import numpy as np

from diacc.config import preset_road
from diacc.envs.action_mask import with_action_mask
from diacc.envs.env import BottleneckEnv, EnvConfig, StepResult, decide
from diacc.envs.metrics import EpisodeRecorder
from diacc.envs.observation import ActorObs, CriticState, ObservationBuilder, stack, unstack
from diacc.envs.reward import reward_terms
from diacc.envs.safety import safety_critical_events
from diacc.runlog import join_parent_log, log
from diacc.sim.backends.base import Backend, BackendError, backend_class
from diacc.sim.maps import load_map
from diacc.sim.state import TrafficState
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
class EnvStep:
    """One environment's transition, after any automatic reset."""

    actor_obs: ActorObs  # first observation of the next episode if the episode ended
    critic_state: CriticState
    ego: np.ndarray  # (C,) ego reward r_e of each CAV slot (0 off the road)
    global_reward: float  # r_g
    completion: float  # r_done
    delay: float  # delay term before its weight
    terminated: bool
    truncated: bool
    alive: np.ndarray  # (C,) bool: CAV on the road after the step (the reward's mask)
    refined_action: np.ndarray  # (C,) int64
    psar_rule_mask: np.ndarray  # (C,) int8 bitmask of PSAR rules that took effect
    final_critic_state: CriticState | None  # state where the episode ended
    episode: dict | None  # metrics of the episode that just ended
    reward_terms: dict[str, float] | None = None  # logged parts of the step's reward
    restarted: bool = False  # the simulator crashed: episode cut, no reward terms
    final_actor_obs: ActorObs | None = None  # observations where the episode ended
    slot_start: np.ndarray | None = None  # (C,) bool: a new CAV took the slot (None: none did)


@dataclass
class VectorStep:
    """Stacked :class:`EnvStep` of E environments.

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


class EnvRunner:
    """One environment with auto-reset, seeding, metrics and crash recovery."""

    def __init__(
        self, config: EnvConfig, run_seed: int, env_index: int, backend: Backend | None = None
    ) -> None:
        """``backend``: the env's simulator (one env of a batch), by default its own."""
        self.config, self.run_seed, self.env_index = config, run_seed, env_index
        self.env = BottleneckEnv(config, backend=backend)
        self.episode = 0

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Start a new episode; ``first_episode`` restarts the episode (seed) counter."""
        if first_episode is not None:
            self.episode = first_episode
        seed = episode_seed(self.run_seed, self.env_index, self.episode)
        self.episode += 1
        actor, critic = self.env.reset_arrays(seed)
        self.recorder = EpisodeRecorder(
            self.env.road, self.config.events, self.config.scenario.warmup_s
        )
        self.recorder.record(self.env.state_)
        return actor, critic

    def step(self, actions: np.ndarray) -> EnvStep:
        try:
            out = self.env.step_arrays(actions)
        except BackendError:
            # The step never happened: bootstrap from the last state that did.
            final = self.env.builder.critic()
            return _cut_episode(*self.reset(), self.env.n_cavs, final)
        return self.finish(out)

    def finish(self, out: StepResult, critical: np.ndarray | None = None) -> EnvStep:
        """Book one step's result; a new episode starts if this one ended.

        ``critical``: the state's safety-critical events if already detected
        (:meth:`EpisodeRecorder.record`). The episode's metrics hold no return:
        that sums team rewards, which the trainer makes at its temperature.
        """
        self.recorder.record(out.state, psar=out.psar, critical=critical)
        final, final_actor, episode = None, None, None
        actor, critic = out.actor_obs, out.critic_state
        if out.terminated or out.truncated:
            final, final_actor = critic, actor
            episode = {
                "length": self.env.steps,
                "collision": float(len(out.state.collisions) > 0),
                **self.recorder.summary().as_dict(),
            }
            actor, critic = self.reset()
        return EnvStep(
            actor_obs=actor,
            critic_state=critic,
            ego=out.ego,
            global_reward=out.global_reward,
            completion=out.completion,
            delay=out.delay,
            terminated=out.terminated,
            truncated=out.truncated,
            alive=out.alive,
            refined_action=out.refined_action,
            psar_rule_mask=out.psar_rule_mask,
            final_critic_state=final,
            episode=episode,
            reward_terms=out.reward_terms,
            final_actor_obs=final_actor,
            slot_start=self.env.slot_start.copy(),
        )

    def close(self) -> None:
        self.env.close()


def _cut_episode(
    actor: ActorObs, critic: CriticState, n_cavs: int, final_critic: CriticState | None
) -> EnvStep:
    """The transition reported when a simulator crashed: episode cut, no reward, fresh start.

    No CAV is on the road and every reward term is 0, so the team reward is 0
    at any temperature.

    A crash is not the episode's end but ours, so it is a *truncation*: the
    trainer bootstraps from ``final_critic``, the last state the simulator
    reached (a termination would teach the critic that a crash is worth 0).
    """
    return EnvStep(
        actor_obs=actor,
        critic_state=critic,
        ego=np.zeros(n_cavs),
        global_reward=0.0,
        completion=0.0,
        delay=0.0,
        terminated=False,
        truncated=True,
        alive=np.zeros(n_cavs, bool),
        refined_action=np.zeros(n_cavs, np.int64),
        psar_rule_mask=np.zeros(n_cavs, np.int8),
        final_critic_state=final_critic,
        episode=None,
        reward_terms=None,
        restarted=True,
    )


def _stack_steps(steps: list[EnvStep]) -> VectorStep:
    return VectorStep(
        actor_obs=stack([s.actor_obs for s in steps]),
        critic_state=stack([s.critic_state for s in steps]),
        ego=np.stack([s.ego for s in steps]),
        global_reward=np.array([s.global_reward for s in steps]),
        completion=np.array([s.completion for s in steps]),
        delay=np.array([s.delay for s in steps]),
        terminated=np.array([s.terminated for s in steps]),
        truncated=np.array([s.truncated for s in steps]),
        alive=np.stack([s.alive for s in steps]),
        refined_action=np.stack([s.refined_action for s in steps]),
        psar_rule_mask=np.stack([s.psar_rule_mask for s in steps]),
        final_critic_state=[s.final_critic_state for s in steps],
        final_actor_obs=[s.final_actor_obs for s in steps],
        episodes={e: s.episode for e, s in enumerate(steps) if s.episode is not None},
        reward_terms={
            key: np.array([s.reward_terms[key] for s in steps if s.reward_terms])
            for key in next((s.reward_terms for s in steps if s.reward_terms), {})
        },
        restarted=np.array([s.restarted for s in steps]),
        restarts=sum(s.restarted for s in steps),
        slot_start=np.stack(
            [np.zeros(len(s.alive), bool) if s.slot_start is None else s.slot_start for s in steps]
        ),
    )


class SyncVectorEnv:
    """Environments stepped one after another in this process.

    ``env_indices`` picks which of the run's environments this object holds
    (all of ``range(n_envs)`` by default); worker processes hold a group each.
    ``env_maps``: the map of each of the run's environments (``config.map`` for all
    by default; :func:`maps_of_envs`).
    """

    def __init__(
        self,
        config: EnvConfig,
        n_envs: int,
        run_seed: int,
        env_indices: list[int] | None = None,
        env_maps: list[str] | None = None,
    ) -> None:
        indices = list(range(n_envs)) if env_indices is None else env_indices
        self.runners = [
            EnvRunner(config if env_maps is None else replace(config, map=env_maps[e]), run_seed, e)
            for e in indices
        ]
        self.n_envs, self.n_cavs = len(indices), config.scenario.n_slots

    def reset_list(self, first_episode: int | None = None) -> list[tuple[ActorObs, CriticState]]:
        return [r.reset(first_episode) for r in self.runners]

    def step_list(self, actions: np.ndarray) -> list[EnvStep]:  # actions (E, C)
        return [r.step(a) for r, a in zip(self.runners, actions, strict=True)]

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Reset every environment (optionally restarting their episode counters)."""
        return _stack_pairs(self.reset_list(first_episode))

    def step(self, actions: np.ndarray) -> VectorStep:  # actions (E, C)
        return _stack_steps(self.step_list(actions))

    def close(self) -> None:
        for r in self.runners:
            r.close()


class BatchedVectorEnv(SyncVectorEnv):
    """Environments whose simulations are rows of one batched ``highway`` backend.

    Each step: one :func:`~diacc.envs.env.decide` call turns all envs' actions into
    commands (PSAR on the batch of their states), one
    :meth:`~diacc.sim.backends.highway.backend.HighwayBackend.step_batch` call
    simulates all envs, and one call each builds every env's observations
    (:meth:`ObservationBuilder.observe_batch`), reward terms
    (:func:`~diacc.envs.reward.reward_terms`) and safety events for the metrics; each env
    then decides whether its episode ended. Results are the same as
    :class:`SyncVectorEnv`'s.
    """

    def __init__(
        self, config: EnvConfig, n_envs: int, run_seed: int, env_indices: list[int] | None = None
    ) -> None:
        """``env_indices``: the run's envs held (their seeds); ``range(n_envs)`` by default."""
        from diacc.sim.backends.highway.backend import BatchSlot, HighwayBackend

        if config.backend != "highway":
            raise ValueError(f"vector mode batched needs the highway backend, not {config.backend}")
        indices = list(range(n_envs)) if env_indices is None else env_indices
        road = preset_road(load_map(config.map), config.sim.style_preset)
        self.batch = HighwayBackend(road, config.sim, n_envs=len(indices))
        self.runners = [
            EnvRunner(config, run_seed, e, BatchSlot(self.batch, row))
            for row, e in enumerate(indices)
        ]
        self.config, self.n_envs, self.n_cavs = config, len(indices), config.scenario.n_slots

    def step_list(self, actions: np.ndarray) -> list[EnvStep]:  # actions (E, C)
        envs = [r.env for r in self.runners]
        state = TrafficState.stack([env.state_ for env in envs])  # (E, V) arrays
        cav_index = np.stack([env.cav_index for env in envs])  # (E, C)
        decision = decide(state, cav_index, actions, self.config, self.batch.road)
        states = self.batch.step_batch(decision.commands)
        decisions = [decision.env(e) for e in range(self.n_envs)]
        for env, d, s in zip(envs, decisions, states, strict=True):
            env.enter(d, s)
        cav_index = np.stack([env.cav_index for env in envs])  # (E, C) slots refilled by enter
        after = TrafficState.stack(states)  # (E, V) arrays
        actor, critic = ObservationBuilder.observe_batch(
            [env.builder for env in envs],
            cav_index,
            np.stack([env.action_memory for env in envs]),  # (E, C, 2)
            np.stack([env.last_refined for env in envs]),  # (E, V)
            after,
        )
        actor = with_action_mask(actor, after, cav_index, self.config, self.batch.road)
        terms = reward_terms(after, cav_index, self.batch.road, self.config.reward)
        critical = safety_critical_events(after, self.config.events).any  # (E, V)
        return [
            r.finish(
                r.env.conclude(d, s, unstack(actor, e), unstack(critic, e), terms.env(e)),
                critical[e],
            )
            for e, (r, d, s) in enumerate(zip(self.runners, decisions, states, strict=True))
        ]


class MapGroupsVectorEnv(SyncVectorEnv):
    """Environments on several maps: one :class:`BatchedVectorEnv` per map, stepped in turn.

    A batched simulator shares one road, so each map gets its own batch, holding a
    contiguous block of the run's environments (:func:`maps_of_envs`); their steps
    concatenate in environment order.
    """

    def __init__(self, config: EnvConfig, n_envs: int, run_seed: int, env_maps: list[str]) -> None:
        maps = list(dict.fromkeys(env_maps))  # in order of first appearance
        self.groups = [
            BatchedVectorEnv(
                replace(config, map=m),
                n_envs,
                run_seed,
                [e for e in range(n_envs) if env_maps[e] == m],
            )
            for m in maps
        ]
        self.runners = [r for g in self.groups for r in g.runners]
        self.n_envs, self.n_cavs = n_envs, config.scenario.n_slots

    def reset_list(self, first_episode: int | None = None) -> list[tuple[ActorObs, CriticState]]:
        return [pair for g in self.groups for pair in g.reset_list(first_episode)]

    def step_list(self, actions: np.ndarray) -> list[EnvStep]:  # actions (E, C)
        steps, start = [], 0
        for g in self.groups:
            steps += g.step_list(actions[start : start + g.n_envs])
            start += g.n_envs
        return steps


def _stack_pairs(pairs: list[tuple[ActorObs, CriticState]]) -> tuple[ActorObs, CriticState]:
    return stack([p[0] for p in pairs]), stack([p[1] for p in pairs])


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
    for runner in group.runners:
        runner.episode = episode
    try:
        while True:
            command, payload = conn.recv()
            if command == "step":
                conn.send(group.step_list(payload))
            elif command == "reset":
                conn.send(group.reset_list(payload))
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

    def _restart(self, w: int) -> list[EnvStep]:
        """Replace a dead worker; every episode of its group is cut."""
        self._replace(w)
        finals = [self._last_critic[e] for e in self.groups[w]]
        return [
            _cut_episode(a, c, self.n_cavs, final)
            for (a, c), final in zip(self._call(w, ("reset", None)), finals, strict=True)
        ]

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
            pairs += reply
        self._last_critic = [critic for _, critic in pairs]
        return _stack_pairs(pairs)

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
        steps: list[EnvStep] = []
        for w, ok in enumerate(sent):
            reply = self._receive(w) if ok else None
            steps += reply if reply is not None else self._restart(w)
        self._last_critic = [s.critic_state for s in steps]
        return _stack_steps(steps)

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
        if env_maps is None:
            return BatchedVectorEnv(config, n_envs, run_seed)
        return MapGroupsVectorEnv(config, n_envs, run_seed, env_maps)
    if mode == "process":
        return ProcessVectorEnv(config, n_envs, run_seed, env_maps=env_maps)
    raise ValueError(f"unknown vector mode {mode!r}; choose sync, batched, process or auto")
