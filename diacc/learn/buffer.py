"""Rollout storage and generalised advantage estimation (GAE).

Shapes: S rollout steps, E environments, C CAV slots per environment. The
team reward, the critic's value and the episode flags are per environment
(S, E); actions, log-probabilities and the alive mask are per CAV (S, E, C).
Observations are stored as stacked containers (see :mod:`diacc.envs.observation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def compute_gae(
    rewards: np.ndarray,  # (S, E)
    values: np.ndarray,  # (S, E) V(s_t)
    next_values: np.ndarray,  # (E,) V(s_S) of the state after the last step
    terminated: np.ndarray,  # (S, E) bool: episode ended at t, no future value
    truncated: np.ndarray,  # (S, E) bool: time limit at t, future value = final_values
    final_values: np.ndarray,  # (S, E) V of the final state of an episode truncated at t
    gamma: float,
    gae_lambda: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Advantages and returns, keeping termination and truncation apart.

    On termination there is no future, so the bootstrap is 0. On truncation
    (the time limit) the episode *could* go on, so it bootstraps from the value
    of the state where it was cut (``final_values``) instead of from the next
    episode's first state; in both cases the trace does not carry across.
    """
    n_steps = rewards.shape[0]
    advantages = np.zeros_like(rewards, dtype=np.float64)
    last = np.zeros(rewards.shape[1:], dtype=np.float64)  # (E,) or (E, C)
    for t in reversed(range(n_steps)):
        ended = terminated[t] | truncated[t]
        following = next_values if t == n_steps - 1 else values[t + 1]
        bootstrap = np.where(truncated[t], final_values[t], np.where(terminated[t], 0.0, following))
        delta = rewards[t] + gamma * bootstrap - values[t]
        last = delta + gamma * gae_lambda * (~ended) * last
        advantages[t] = last
    return advantages, advantages + values


@dataclass
class Rollout:
    """One rollout of S steps from E environments (numpy, filled step by step)."""

    actor_obs: list  # S stacked ActorObs, fields (E, C, ...)
    critic_state: list  # S stacked CriticState, fields (E, ...)
    actions: np.ndarray  # (S, E, C) int64 proposed action (executed: env.psar_actions)
    logprobs: np.ndarray  # (S, E, C)
    alive: np.ndarray  # (S, E, C) bool: CAV on the road when acting
    values: np.ndarray  # (S, E) de-normalised V(s_t), for GAE; (S, E, C) per agent
    values_normalised: np.ndarray  # (S, E) the critic's raw output: the value-clip centre
    rewards: np.ndarray  # (S, E)
    terminated: np.ndarray  # (S, E) bool
    truncated: np.ndarray  # (S, E) bool
    final_values: np.ndarray  # (S, E), or (S, E, C) per agent
    episode_start: np.ndarray  # (S, E) bool: s_t is the first state of an episode
    agent_start: np.ndarray  # (S, E, C) bool: episode start, or a new CAV in the slot at s_t
    actor_hidden: np.ndarray  # (S, E, C, H) hidden state *before* step t
    critic_hidden: np.ndarray  # (S, E, H)
    # Filled by the rollout for the values computed after it (mappo.rollout_values):
    cut_states: list  # (t, env, final CriticState, final ActorObs) of each truncated episode
    next_actor_obs: object = None  # stacked ActorObs of s_S, the state after the last step
    next_critic_state: object = None  # stacked CriticState of s_S

    @classmethod
    def allocate(
        cls, steps: int, envs: int, cavs: int, actor_h: int, critic_h: int, per_agent: bool = False
    ) -> Rollout:
        """``per_agent``: values (S, E, C), one per CAV slot (``critic_values="per_agent"``)."""
        f = np.float32
        v = (steps, envs, cavs) if per_agent else (steps, envs)
        return cls(
            actor_obs=[None] * steps,
            critic_state=[None] * steps,
            actions=np.zeros((steps, envs, cavs), np.int64),
            logprobs=np.zeros((steps, envs, cavs), f),
            alive=np.zeros((steps, envs, cavs), bool),
            values=np.zeros(v, np.float64),
            values_normalised=np.zeros(v, f),
            rewards=np.zeros((steps, envs), np.float64),
            terminated=np.zeros((steps, envs), bool),
            truncated=np.zeros((steps, envs), bool),
            final_values=np.zeros(v, np.float64),
            episode_start=np.zeros((steps, envs), bool),
            agent_start=np.zeros((steps, envs, cavs), bool),
            actor_hidden=np.zeros((steps, envs, cavs, actor_h), f),
            critic_hidden=np.zeros((steps, envs, critic_h), f),
            cut_states=[],
        )
