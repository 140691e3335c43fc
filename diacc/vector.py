"""Many environments stepped as one batch: in-process or in worker processes.

Both flavours run the same :class:`EnvRunner` per environment, which adds
what the trainer needs around :class:`~diacc.env.BottleneckEnv`: automatic
reset with per-episode seeds derived from the run seed, the final critic
state of each finished episode (to bootstrap truncated episodes), episode
metrics, and recovery from a crashed simulator.

* :class:`SyncVectorEnv` steps environments one after another in this
  process. Best for the ``highway`` backend, whose step is a few hundred
  microseconds: pipes would cost more than they save.
* :class:`ProcessVectorEnv` keeps one environment per worker process
  (``spawn`` start method; libsumo allows one simulation per process), so
  environments step in parallel. A worker that dies is restarted; its episode
  is cut (``terminated`` with zero reward) and counted in ``restarts``.
"""

from __future__ import annotations

import multiprocessing as mp
from dataclasses import dataclass

import numpy as np

from diacc.backends.base import BackendError
from diacc.env import BottleneckEnv, EnvConfig
from diacc.metrics import EpisodeRecorder
from diacc.observation import ActorObs, CriticState, stack


def episode_seed(run_seed: int, env_index: int, episode: int) -> int:
    """Independent, reproducible seed for one episode of one environment."""
    # 31 bits: SUMO's --seed takes a signed 32-bit integer.
    return int(np.random.SeedSequence([run_seed, env_index, episode]).generate_state(1)[0] >> 1)


@dataclass
class EnvStep:
    """One environment's transition, after any automatic reset."""

    actor_obs: ActorObs  # first observation of the next episode if the episode ended
    critic_state: CriticState
    reward: float
    terminated: bool
    truncated: bool
    alive: np.ndarray  # (C,) bool
    refined_action: np.ndarray  # (C,) int64
    psar_rule_mask: np.ndarray  # (C,) int8 bitmask of PSAR rules that took effect
    final_critic_state: CriticState | None  # state where the episode ended
    episode: dict | None  # metrics of the episode that just ended
    reward_terms: dict[str, float] | None = None  # parts of the step's reward
    restarted: bool = False


@dataclass
class VectorStep:
    """Stacked :class:`EnvStep` of E environments."""

    actor_obs: ActorObs  # fields (E, C, ...)
    critic_state: CriticState  # fields (E, ...)
    reward: np.ndarray  # (E,)
    terminated: np.ndarray  # (E,) bool
    truncated: np.ndarray  # (E,) bool
    alive: np.ndarray  # (E, C) bool
    refined_action: np.ndarray  # (E, C)
    psar_rule_mask: np.ndarray  # (E, C)
    final_critic_state: list[CriticState | None]  # (E,)
    episodes: list[dict]  # metrics of episodes that ended this step
    reward_terms: dict[str, np.ndarray]  # each part of the reward, (E',) over envs that reported it
    restarts: int


class EnvRunner:
    """One environment with auto-reset, seeding, metrics and crash recovery."""

    def __init__(self, config: EnvConfig, run_seed: int, env_index: int) -> None:
        self.config, self.run_seed, self.env_index = config, run_seed, env_index
        self.env = BottleneckEnv(config)
        self.episode = 0
        self.return_ = 0.0

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Start a new episode; ``first_episode`` restarts the episode (seed) counter."""
        if first_episode is not None:
            self.episode = first_episode
        seed = episode_seed(self.run_seed, self.env_index, self.episode)
        self.episode += 1
        self.return_ = 0.0
        actor, critic = self.env.reset_arrays(seed)
        self.recorder = EpisodeRecorder(self.env.road, self.config.events)
        self.recorder.record(self.env.state_)
        return actor, critic

    def set_temperature(self, tau: float) -> None:
        self.env.temperature = tau

    def step(self, actions: np.ndarray) -> EnvStep:
        try:
            out = self.env.step_arrays(actions)
        except BackendError:
            return _cut_episode(*self.reset(), self.env.n_cavs)
        self.return_ += out.reward
        self.recorder.record(out.state, psar=out.psar)
        final, episode = None, None
        actor, critic = out.actor_obs, out.critic_state
        if out.terminated or out.truncated:
            final = critic
            episode = {
                "return": self.return_,
                "length": self.env.steps,
                "collision": float(len(out.state.collisions) > 0),
                **self.recorder.summary().as_dict(),
            }
            actor, critic = self.reset()
        return EnvStep(
            actor,
            critic,
            out.reward,
            out.terminated,
            out.truncated,
            out.alive,
            out.refined_action,
            out.psar_rule_mask,
            final,
            episode,
            out.reward_terms,
        )

    def close(self) -> None:
        self.env.close()


def _cut_episode(actor: ActorObs, critic: CriticState, n_cavs: int) -> EnvStep:
    """The transition reported when a simulator crashed: episode cut, no reward, fresh start."""
    return EnvStep(
        actor,
        critic,
        0.0,
        True,
        False,
        np.zeros(n_cavs, bool),
        np.zeros(n_cavs, np.int64),
        np.zeros(n_cavs, np.int8),
        None,
        None,
        None,
        True,
    )


def _stack_steps(steps: list[EnvStep]) -> VectorStep:
    return VectorStep(
        actor_obs=stack([s.actor_obs for s in steps]),
        critic_state=stack([s.critic_state for s in steps]),
        reward=np.array([s.reward for s in steps]),
        terminated=np.array([s.terminated for s in steps]),
        truncated=np.array([s.truncated for s in steps]),
        alive=np.stack([s.alive for s in steps]),
        refined_action=np.stack([s.refined_action for s in steps]),
        psar_rule_mask=np.stack([s.psar_rule_mask for s in steps]),
        final_critic_state=[s.final_critic_state for s in steps],
        episodes=[s.episode for s in steps if s.episode is not None],
        reward_terms={
            key: np.array([s.reward_terms[key] for s in steps if s.reward_terms])
            for key in next((s.reward_terms for s in steps if s.reward_terms), {})
        },
        restarts=sum(s.restarted for s in steps),
    )


class SyncVectorEnv:
    """E environments stepped one after another in this process."""

    def __init__(self, config: EnvConfig, n_envs: int, run_seed: int) -> None:
        self.runners = [EnvRunner(config, run_seed, e) for e in range(n_envs)]
        self.n_envs, self.n_cavs = n_envs, config.scenario.n_cavs

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Reset every environment (optionally restarting their episode counters)."""
        pairs = [r.reset(first_episode) for r in self.runners]
        return stack([p[0] for p in pairs]), stack([p[1] for p in pairs])

    def step(self, actions: np.ndarray) -> VectorStep:  # actions (E, C)
        return _stack_steps([r.step(a) for r, a in zip(self.runners, actions, strict=True)])

    def set_temperature(self, tau: float) -> None:
        for r in self.runners:
            r.set_temperature(tau)

    def close(self) -> None:
        for r in self.runners:
            r.close()


def _worker(conn, config: EnvConfig, run_seed: int, env_index: int, episode: int) -> None:
    runner = EnvRunner(config, run_seed, env_index)
    runner.episode = episode
    try:
        while True:
            command, payload = conn.recv()
            if command == "step":
                conn.send(runner.step(payload))
            elif command == "reset":
                conn.send(runner.reset(payload))
            elif command == "tau":
                runner.set_temperature(payload)
            elif command == "close":
                break
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        runner.close()
        conn.close()


class ProcessVectorEnv:
    """E environments, one per worker process, stepped in parallel."""

    def __init__(self, config: EnvConfig, n_envs: int, run_seed: int) -> None:
        self.config, self.run_seed = config, run_seed
        self.n_envs, self.n_cavs = n_envs, config.scenario.n_cavs
        self.ctx = mp.get_context("spawn")
        self.tau = config.reward.tau_init
        self.restarts = 0
        self.workers: list = [None] * n_envs
        self.pipes: list = [None] * n_envs
        for e in range(n_envs):
            self._start(e, episode=0)

    def _start(self, e: int, episode: int) -> None:
        parent, child = self.ctx.Pipe()
        proc = self.ctx.Process(
            target=_worker, args=(child, self.config, self.run_seed, e, episode), daemon=True
        )
        proc.start()
        child.close()
        self.workers[e], self.pipes[e] = proc, parent
        parent.send(("tau", self.tau))

    def _restart(self, e: int) -> tuple[ActorObs, CriticState]:
        self.restarts += 1
        self.workers[e].kill()
        self.workers[e].join()
        # Episode numbers keep counting up, so a restarted env never repeats a seed.
        self._start(e, episode=1_000_000 + self.restarts)
        self.pipes[e].send(("reset", None))
        return self.pipes[e].recv()

    def reset(self, first_episode: int | None = None) -> tuple[ActorObs, CriticState]:
        """Reset every environment (optionally restarting their episode counters)."""
        for p in self.pipes:
            p.send(("reset", first_episode))
        pairs = [p.recv() for p in self.pipes]
        return stack([p[0] for p in pairs]), stack([p[1] for p in pairs])

    def step(self, actions: np.ndarray) -> VectorStep:
        crashed = set()
        for e, (p, a) in enumerate(zip(self.pipes, actions, strict=True)):
            try:
                p.send(("step", a))
            except (ConnectionError, OSError):
                crashed.add(e)
        steps = []
        for e, p in enumerate(self.pipes):
            if e not in crashed:
                try:
                    steps.append(p.recv())
                    continue
                except (EOFError, ConnectionError, OSError):
                    pass
            steps.append(_cut_episode(*self._restart(e), self.n_cavs))
        return _stack_steps(steps)

    def set_temperature(self, tau: float) -> None:
        self.tau = tau
        for p in self.pipes:
            p.send(("tau", tau))

    def close(self) -> None:
        for p, w in zip(self.pipes, self.workers, strict=True):
            try:
                p.send(("close", None))
            except (BrokenPipeError, OSError):
                pass
            w.join(timeout=5)
            if w.is_alive():
                w.kill()


def make_vector_env(config: EnvConfig, n_envs: int, run_seed: int, mode: str = "auto"):
    """``mode``: ``sync``, ``process`` or ``auto`` (sync for highway, process for sumo)."""
    if mode == "auto":
        mode = "sync" if config.backend == "highway" else "process"
    if mode == "sync":
        return SyncVectorEnv(config, n_envs, run_seed)
    if mode == "process":
        return ProcessVectorEnv(config, n_envs, run_seed)
    raise ValueError(f"unknown vector mode {mode!r}; choose sync, process or auto")
