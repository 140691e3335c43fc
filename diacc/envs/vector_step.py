"""What a vector env's step returns (:class:`VectorStep`), and how steps of groups join.

Shared by every flavour of :mod:`diacc.envs.vector`, in this process or in
worker processes (:mod:`diacc.envs.vector_process`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.envs.observation import ActorObs, CriticState, concat
from diacc.envs.reward import AnnealedTeamReward, TeamReward


@dataclass
class VectorStep:
    """One step of E environments, after the automatic resets.

    ``team`` is the step's team reward R (:func:`score`):
    :func:`~diacc.envs.reward.team_reward` of ``ego``, ``alive``,
    ``global_reward``, ``completion`` and ``delay`` at the schedule's temperature.
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
    team: TeamReward | None = None  # R (E,) and its softmin parts; None before score()


def score(out: VectorStep, reward: AnnealedTeamReward) -> VectorStep:
    """``out`` with its team reward at ``reward``'s temperature; counts the E env steps.

    A crashed env's terms are 0 and no CAV is on the road, so its R is 0.
    """
    out.team = reward(out.ego, out.alive, out.global_reward, out.completion, out.delay)
    reward.advance(len(out.terminated))
    return out


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
