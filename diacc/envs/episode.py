"""Single episodes, played the one way every command plays them: through the environment.

Evaluation, the non-learning baselines, ``diacc simulate``, ``diacc render``,
the safety benchmark and the tests drive :class:`EpisodeDriver`; training
steps the same environment in vectors (:mod:`diacc.envs.vector`). So an episode
always ends by the environment's rule (:meth:`BottleneckEnv.step_arrays`:
a collision, every vehicle gone, or ``episode_steps``), written once.

Policies that send no commands (the baselines, whose CAVs do not exist or
drive themselves) answer ``remain`` for every CAV, which the backends turn
into the idle command.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from diacc.config import EnvConfig
from diacc.envs.actions import ACTION_NAMES
from diacc.envs.env import BottleneckEnv
from diacc.envs.metrics import EpisodeRecorder
from diacc.envs.observation import ActorObs
from diacc.envs.psar import PSARResult
from diacc.sim.state import TrafficState


class CavPolicy(Protocol):
    """What drives the CAVs of an episode (:class:`diacc.experiments.policies.Policy` and
    test doubles)."""

    def begin_episode(self, n_cavs: int, seed: int) -> None: ...

    def act(self, actor_obs: ActorObs, first_step: bool | np.ndarray) -> np.ndarray: ...


class EpisodeDriver:
    """Runs episodes of one policy in one environment configuration."""

    def __init__(self, policy: CavPolicy, cfg: EnvConfig) -> None:
        self.policy, self.cfg = policy, cfg
        self.env = BottleneckEnv(cfg)
        self.road, self.backend = self.env.road, self.env.backend
        self.state: TrafficState | None = None
        use_road = getattr(policy, "use_road", None)  # optional: policies that read the map
        if use_road is not None:  # the map as the agents see it (diacc.envs.lateral_frame)
            use_road(self.env.batch.builder.road)
        use_env = getattr(policy, "use_env", None)  # optional: policies on PettingZoo dicts
        if use_env is not None:
            use_env(self.env)

    def reset(self, seed: int) -> TrafficState:
        """Start the episode of ``seed`` (traffic and, for scripted policies, their draws)."""
        self.steps, self.done = 0, False
        self._obs, _ = self.env.reset_arrays(seed)
        self.state = self.env.state_
        self.policy.begin_episode(self.env.n_cavs, seed)
        self.psar_rule = np.zeros(self.state.n_vehicles, np.int8)  # (V,) 0 for HDVs
        self.psar: PSARResult | None = None
        # (A,) how often the policy picked each action for a living CAV (before PSAR):
        # what shows a policy that acts alike whatever it sees (diacc.learn.collapse)
        self.picked = np.zeros(len(ACTION_NAMES), np.int64)
        return self.state

    def step(self) -> TrafficState:
        """Advance one decision step; sets :attr:`done`, :attr:`psar_rule`, :attr:`psar` and
        :attr:`picked`."""
        assert self.state is not None and not self.done, "reset() before step()"
        # (C,) slots whose CAV acts first now: all at the start, refilled ones later (demand).
        first_step = (self.steps == 0) | self.env.slot_start
        actions = self.policy.act(self._obs, first_step=first_step)
        alive_before = self._obs.alive.copy()  # (C,)
        acting = self.env.cav_index.copy()  # (C,) before slots are refilled (demand)
        out = self.env.step_arrays(actions)  # checks the actions
        self.picked += np.bincount(
            np.asarray(actions, np.int64)[alive_before], minlength=len(ACTION_NAMES)
        )
        self._obs = out.actor_obs
        self.psar_rule = np.zeros(out.state.n_vehicles, np.int8)
        self.psar_rule[acting] = np.where(alive_before, out.psar_rule, 0)
        self.psar = out.psar
        self.steps += 1
        self.state, self.done = out.state, out.terminated or out.truncated
        return self.state

    def close(self) -> None:
        self.env.close()


def play_episode(driver: EpisodeDriver, seed: int) -> EpisodeRecorder:
    """Play one seeded episode to its end; the recorder holds every state (the metrics' input).

    It records the env's batch of one as the env steps it (:attr:`BottleneckEnv.traffic`,
    :attr:`BottleneckEnv.transition`), not the driver's one-env view of it.
    """
    recorder = EpisodeRecorder(driver.road, driver.cfg.events, driver.cfg.scenario.warmup_s)
    env = driver.env
    driver.reset(seed)
    recorder.record(env.traffic)
    while not driver.done:
        driver.step()
        recorder.record(env.transition.state, psar=env.transition.psar)
    return recorder
