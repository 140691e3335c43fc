"""What a step returns (:class:`Transition`), in every layer, and how steps of groups join.

One type for the step of E envs (:meth:`diacc.envs.batch.EnvBatch.step`), the
step of a vector env after its automatic resets (:mod:`diacc.envs.vector`, in
this process or in worker processes: :mod:`diacc.envs.vector_process`) and the
PettingZoo env's step (:meth:`diacc.envs.env.BottleneckEnv.step_arrays`, one
env's view, :meth:`Transition.env`). The layers fill what they know:

- the batch's step: the state reached, PSAR's full result and the safety events;
- a vector step: the episodes that ended and their last observations, the
  logged reward parts and the restarts, and no state (its ended envs' rows
  already hold their next episode's first observations);
- a scored step (:func:`score`, ``step_arrays``): the team reward ``team``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from diacc.config import RewardConfig
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.psar import PSARResult
from diacc.envs.reward import RewardTerms, TeamReward, team_reward
from diacc.records import where_rows
from diacc.sim.state import TrafficState


@dataclass
class Transition:
    """One step of E envs (C = agent slots); in one env's view (:meth:`env`) the env
    axis is gone ((C,) arrays, bools and floats)."""

    actor_obs: ActorObs  # (E, C, ...) observations of the state reached (or of a new episode)
    critic_state: CriticState  # (E, ...)
    terms: RewardTerms  # (E, C) and (E,): the reward's parts that need no temperature, and
    # ``terms.alive`` (E, C): CAV scored (on the road, or removed by a crash in the step)
    refined_action: np.ndarray  # (E, C) int64 action executed
    psar_rule: np.ndarray  # (E, C) int8 last PSAR rule that took effect (0 none)
    psar_rule_mask: np.ndarray  # (E, C) int8 bitmask of the rules that took effect
    slot_start: np.ndarray  # (E, C) bool a new CAV took the slot; its next action starts afresh
    terminated: np.ndarray  # (E,) bool a collision, or every vehicle gone
    truncated: np.ndarray  # (E,) bool episode_steps reached (or the simulator crashed: vector)
    crashed: np.ndarray  # (E,) bool the simulator failed: nothing of the row is valid (a
    # vector env restarted it and reports no reward for it)
    # ---- the batch's step (None in a vector step)
    state: TrafficState | None = None  # (E, V) the state reached
    psar: PSARResult | None = None  # full PSAR result, (E, C) fields (None when PSAR is off)
    critical: np.ndarray | None = None  # (E, V) bool safety-critical events (p(SCE))
    # ---- a vector step
    final_critic_state: list[CriticState | None] = field(default_factory=list)  # (E,)
    final_actor_obs: list[ActorObs | None] = field(default_factory=list)  # (E,) (None after
    # a simulator crash)
    episodes: dict[int, dict] = field(default_factory=dict)  # env -> metrics of the episode
    # that ended there this step
    reward_terms: dict = field(default_factory=dict)  # logged parts of the reward: (E',) over
    # the envs whose step happened (vector), floats (one env's view)
    restarts: int = 0  # simulators restarted after a crash
    # ---- a scored step
    team: TeamReward | None = None  # R (E,) and its softmin parts (:func:`score`)

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
    def reward(self):
        """(E,) the team reward R (``team.total``; a float in one env's view; NaN before
        the step is scored)."""
        return float("nan") if self.team is None else self.team.total

    def env(self, e: int) -> Transition:
        """Env ``e``'s view of a batch's step (the PettingZoo env's)."""

        def row(value):
            return None if value is None else value[e]

        return Transition(
            actor_obs=self.actor_obs.unbatched(e),
            critic_state=self.critic_state.unbatched(e),
            terms=self.terms.unbatched(e),
            refined_action=self.refined_action[e],
            psar_rule=self.psar_rule[e],
            psar_rule_mask=self.psar_rule_mask[e],
            slot_start=self.slot_start[e],
            terminated=bool(self.terminated[e]),
            truncated=bool(self.truncated[e]),
            crashed=bool(self.crashed[e]),
            state=None if self.state is None else self.state.env(e),
            psar=None if self.psar is None else self.psar.unbatched(e),
            critical=row(self.critical),
            reward_terms={k: float(v[0]) for k, v in self.logged_terms(np.array([e])).items()},
        )

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


def score(out: Transition, tau: float, cfg: RewardConfig) -> Transition:
    """``out`` with its team reward at softmin temperature ``tau`` (the envs' own).

    A crashed env's terms are 0 and no CAV is on the road, so its R is 0.
    """
    out.team = team_reward(
        out.ego, out.alive, out.global_reward, out.completion, out.delay, tau, cfg
    )
    return out


def kept_rows(out: Transition, kept: np.ndarray) -> Transition:
    """``out`` with the reward terms and PSAR outcome of the envs not ``kept`` (E,) set to 0
    (their simulator crashed: nothing of the step happened); ``out`` itself if all are kept."""
    if kept.all():
        return out
    return replace(
        out,
        terms=out.terms.where_rows(kept),
        refined_action=where_rows(out.refined_action, kept),
        psar_rule=where_rows(out.psar_rule, kept),
        psar_rule_mask=where_rows(out.psar_rule_mask, kept),
    )


def concat_steps(parts: list[Transition]) -> Transition:
    """Vector steps of groups of envs as one, in group order (env indices follow on)."""
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [len(p.terminated) for p in parts])
    terms = [p.reward_terms for p in parts if p.reward_terms]
    return Transition(
        actor_obs=ActorObs.concat([p.actor_obs for p in parts]),
        critic_state=CriticState.concat([p.critic_state for p in parts]),
        terms=RewardTerms.concat([p.terms for p in parts]),
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


#: Transition's fields that are plain (E, ...) arrays in a vector step.
_ARRAY_FIELDS = (
    "refined_action",
    "psar_rule",
    "psar_rule_mask",
    "slot_start",
    "terminated",
    "truncated",
    "crashed",
)


def cut_steps(
    actor: ActorObs, critic: CriticState, finals: list[CriticState | None], n_cavs: int
) -> Transition:
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
    per_cav, per_env = np.zeros((n, n_cavs)), np.zeros(n)
    return Transition(
        actor_obs=actor,
        critic_state=critic,
        terms=RewardTerms(
            speed=per_cav,
            warning=per_cav,
            collision=per_cav,
            time_penalty=per_cav,
            ego=per_cav,
            alive=np.zeros((n, n_cavs), bool),
            global_reward=per_env,
            completion=per_env,
            trip_end=per_cav,
            delay=per_env,
        ),
        refined_action=np.zeros((n, n_cavs), np.int64),
        psar_rule=np.zeros((n, n_cavs), np.int8),
        psar_rule_mask=np.zeros((n, n_cavs), np.int8),
        slot_start=np.zeros((n, n_cavs), bool),
        terminated=np.zeros(n, bool),
        truncated=np.ones(n, bool),
        crashed=np.ones(n, bool),
        final_critic_state=list(finals),
        final_actor_obs=[None] * n,
        restarts=n,
    )
