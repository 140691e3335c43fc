"""What a step returns, in every layer: the batch's step (:class:`Transition`) and the
vector env's (:class:`VectorStep`), both :class:`~diacc.records.Batched` records.

- :class:`Transition`: the step of E envs (:meth:`diacc.envs.batch.EnvBatch.step`):
  the observations of the state reached, the reward's terms, the state, PSAR's
  full result and the safety events. The PettingZoo env steps a batch of one and
  hands out its one-env view (:meth:`~diacc.records.Batched.unbatched`, in
  :meth:`diacc.envs.env.BottleneckEnv.step_arrays`): the one place the env axis goes.
- :class:`VectorStep`: the step of a vector env after its automatic resets
  (:mod:`diacc.envs.vector`, in this process or in worker processes:
  :mod:`diacc.envs.vector_process`): no state (its ended envs' rows already hold
  their next episode's first observations), but the last observations and the
  metrics of the episodes that ended. Groups of envs join with ``concat``.

Both carry the team reward ``team`` once scored (:func:`score`): the PettingZoo
env and the vector envs score at their temperature; a worker's step is scored by
its parent.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np

from diacc.config import RewardConfig
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.psar import PSARResult
from diacc.envs.reward import RewardTerms, TeamReward, team_reward
from diacc.records import Batched, per_env, per_env_items, per_env_record
from diacc.sim.state import TrafficState


@dataclass
class Step(Batched):
    """What every step of E envs reports (C = agent slots): :class:`Transition` and
    :class:`VectorStep` add their layer's parts."""

    actor_obs: ActorObs = per_env_record()  # (E, C, ...) of the state reached (or a new episode)
    critic_state: CriticState = per_env_record()  # (E, ...)
    terms: RewardTerms = per_env_record()  # the reward's parts that need no temperature, and
    # ``terms.alive`` (E, C): CAV scored (on the road, or removed by a crash in the step)
    refined_action: np.ndarray = per_env("E, C")  # int64 action executed
    psar_rule: np.ndarray = per_env("E, C")  # int8 last PSAR rule that took effect (0 none)
    psar_rule_mask: np.ndarray = per_env("E, C")  # int8 bitmask of the rules that took effect
    slot_start: np.ndarray = per_env("E, C")  # bool a new CAV took the slot: acts afresh
    terminated: np.ndarray = per_env("E")  # bool a collision, or every vehicle gone
    truncated: np.ndarray = per_env("E")  # bool episode_steps reached (or a crash: vector)
    crashed: np.ndarray = per_env("E")  # bool the simulator failed: nothing of the row is
    # valid (a vector env restarted it and reports no reward for it)
    team: TeamReward | None = per_env_record()  # R (E,) and its softmin parts; None until
    # :func:`score`

    # What team_reward aggregates, at any temperature:
    @property
    def ego(self) -> np.ndarray:
        """(E, C) ego reward r_e of each CAV slot (0 off the road)."""
        return self.terms.ego

    @property
    def alive(self) -> np.ndarray:
        """(E, C) bool CAV scored by the reward: on the road after the step, or taken
        off it by a collision in the step (``on_collision = "remove"``)."""
        return self.terms.alive

    @property
    def global_reward(self) -> np.ndarray:
        """(E,) r_g."""
        return self.terms.global_reward

    @property
    def completion(self) -> np.ndarray:
        """(E,) r_done."""
        return self.terms.completion

    @property
    def delay(self) -> np.ndarray:
        """(E,) the delay term before its weight."""
        return self.terms.delay

    @property
    def reward(self) -> np.ndarray:
        """(E,) the team reward R (``team.total``; in one env's view a float, as every
        (E,) field there). An error before the step is scored (:func:`score`)."""
        if self.team is None:
            raise ValueError("this step has no team reward yet: score() it")
        return self.team.total

    @property
    def reward_terms(self) -> dict[str, np.ndarray]:
        """Logged parts of the reward, (E',) each over the envs whose step happened (not
        crashed; {} for none)."""
        return self.logged_terms(np.flatnonzero(~self.crashed))

    def logged_terms(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """Envs ``rows``' reward parts for the logs, (R,) each ({} for no rows; the
        softmin's parts come with the team reward, ``team``)."""
        if len(rows) == 0:
            return {}
        terms, alive = self.terms, self.terms.alive[rows]
        return {
            "individual": _alive_means(terms.ego[rows], alive),
            "global": terms.global_reward[rows].astype(np.float64),
            "completion": terms.completion[rows].astype(np.float64),
            # Logged so that a learning curve shows whether closeness fires.
            "warning": _alive_means(terms.warning[rows], alive),
            "delay": terms.delay[rows].astype(np.float64),
        }


@dataclass
class Transition(Step):
    """The batch's step: what :meth:`~diacc.envs.batch.EnvBatch.step` returns, and (one
    env's view, :meth:`~diacc.records.Batched.unbatched`) the PettingZoo env's."""

    state: TrafficState = per_env_record(keeps_batch=True)  # (E, V) the state reached (a
    # batch of one in one env's view: users index its row 0)
    psar: PSARResult | None = per_env_record()  # (E, C) fields (None when PSAR is off)
    critical: np.ndarray = per_env("E, V")  # bool safety-critical events (p(SCE))


@dataclass
class VectorStep(Step):
    """A vector env's step, after its automatic resets: the rows of ended episodes hold
    their next episode's first observations; their last ones are kept aside."""

    final_critic_state: list[CriticState | None] = per_env_items()  # one env's view of the
    # critic state an episode ended in (or a crashed simulator last reached), else None
    final_actor_obs: list[ActorObs | None] = per_env_items()  # one env's view of the
    # observations an episode ended in (None after a simulator crash), else None
    episode_metrics: list[dict | None] = per_env_items()  # metrics of the episode that
    # ended in the env this step, else None

    @property
    def episodes(self) -> dict[int, dict]:
        """Env -> metrics of the episode that ended there this step."""
        return {e: m for e, m in enumerate(self.episode_metrics) if m is not None}

    @property
    def restarts(self) -> int:
        """Simulators restarted after a crash in this step."""
        return int(np.count_nonzero(self.crashed))


def _alive_means(values: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """(R,) mean of each row of ``values`` (R, C) over its ``alive`` entries, 0 for none.

    Rows with the same number of alive entries are averaged together: a row's
    mean is then bit for bit that of its entries alone (``values[r][alive[r]].mean()``).
    """
    n_cav = values.shape[-1]
    # every CAV on the road: one plain mean (none at all, pure HDV: 0, not 0 / 0)
    if n_cav and np.count_nonzero(alive) == alive.size:
        return (values.sum(axis=-1) / n_cav).astype(np.float64)
    out = np.zeros(len(values))
    counts = alive.sum(axis=-1)  # (R,)
    for n in sorted(set(counts.tolist()) - {0}):
        same = np.flatnonzero(counts == n)
        out[same] = values[same][alive[same]].reshape(len(same), n).sum(axis=-1) / n  # = mean
    return out


Scored = TypeVar("Scored", bound=Step)


def score(out: Scored, tau: float, cfg: RewardConfig) -> Scored:
    """``out`` with its team reward at softmin temperature ``tau`` (the envs' own).

    A crashed env's terms are 0 and no CAV is on the road, so its R is 0.
    """
    team = team_reward(out.ego, out.alive, out.global_reward, out.completion, out.delay, tau, cfg)
    return replace(out, team=team)


def joined(parts: list[VectorStep]) -> VectorStep:
    """Vector steps of groups of envs as one, in group order (env indices follow on; one
    group's step as it is)."""
    return parts[0] if len(parts) == 1 else VectorStep.concat(parts)


def cut_steps(
    actor: ActorObs, critic: CriticState, finals: list[CriticState | None], n_cavs: int
) -> VectorStep:
    """The vector step reported for envs whose simulator crashed: episode cut, no reward,
    fresh start.

    ``actor``/``critic``: the envs' first observations of their new episodes;
    ``finals``: each env's last state before the crash. No CAV is on the road and
    every reward term is 0, so the team reward is 0 at any temperature. A crash is
    not the episode's end but ours, so it is a *truncation*: the trainer
    bootstraps from the last state the simulator reached (a termination would
    teach the critic that a crash is worth 0).
    """
    n = len(finals)
    per_cav, one_per_env = np.zeros((n, n_cavs)), np.zeros(n)
    return VectorStep(
        actor_obs=actor,
        critic_state=critic,
        terms=RewardTerms(
            speed=per_cav,
            warning=per_cav,
            collision=per_cav,
            time_penalty=per_cav,
            ego=per_cav,
            alive=np.zeros((n, n_cavs), bool),
            global_reward=one_per_env,
            completion=one_per_env,
            trip_end=per_cav,
            delay=one_per_env,
        ),
        refined_action=np.zeros((n, n_cavs), np.int64),
        psar_rule=np.zeros((n, n_cavs), np.int8),
        psar_rule_mask=np.zeros((n, n_cavs), np.int8),
        slot_start=np.zeros((n, n_cavs), bool),
        terminated=np.zeros(n, bool),
        truncated=np.ones(n, bool),
        crashed=np.ones(n, bool),
        team=None,
        final_critic_state=list(finals),
        final_actor_obs=[None] * n,
        episode_metrics=[None] * n,
    )
