"""Rollout storage, generalised advantage estimation (GAE) and the update's batch.

Shapes: S rollout steps, E environments, C CAV slots per environment. The
team reward, the critic's value and the episode flags are per environment
(S, E); actions, log-probabilities and the alive mask are per CAV (S, E, C).
Observations are stored as stacked containers (see :mod:`diacc.envs.observation`).
:func:`make_batch` cuts a filled rollout into the time-major sequences the
recurrent update replays (:class:`Batch`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from diacc.envs.observation import ActorObs, CriticState
from diacc.learn.models.agent_value import AGENT_KEY, agent_features
from diacc.learn.models.inputs import to_tensors


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
    rewards: np.ndarray  # (S, E) the team reward R
    # credit = "own": each CAV's reward, and its trip's end at t (arrived, crashed, slot
    # refilled, or no CAV in the slot): no future value for that CAV
    agent_rewards: np.ndarray  # (S, E, C)
    agent_ended: np.ndarray  # (S, E, C) bool
    terminated: np.ndarray  # (S, E) bool
    truncated: np.ndarray  # (S, E) bool
    final_values: np.ndarray  # (S, E), or (S, E, C) per agent
    episode_start: np.ndarray  # (S, E) bool: s_t is the first state of an episode
    agent_start: np.ndarray  # (S, E, C) bool: episode start, or a new CAV in the slot at s_t
    actor_hidden: np.ndarray  # (S, E, C, H) hidden state *before* step t
    critic_hidden: np.ndarray  # (S, E, H)
    # Filled by the rollout for the values computed after it (ppo.rollout_values):
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
            agent_rewards=np.zeros((steps, envs, cavs), np.float64),
            agent_ended=np.zeros((steps, envs, cavs), bool),
            terminated=np.zeros((steps, envs), bool),
            truncated=np.zeros((steps, envs), bool),
            final_values=np.zeros(v, np.float64),
            episode_start=np.zeros((steps, envs), bool),
            agent_start=np.zeros((steps, envs, cavs), bool),
            actor_hidden=np.zeros((steps, envs, cavs, actor_h), f),
            critic_hidden=np.zeros((steps, envs, critic_h), f),
            cut_states=[],
        )


def chunk_time_major(arrays: np.ndarray, chunk_len: int) -> np.ndarray:
    """(S, B, ...) -> (L, S/L * B, ...): sequences of L steps, one per (chunk, b)."""
    steps, batch = arrays.shape[:2]
    out = arrays.reshape(steps // chunk_len, chunk_len, batch, *arrays.shape[2:])
    return out.swapaxes(0, 1).reshape(chunk_len, (steps // chunk_len) * batch, *arrays.shape[2:])


@dataclass
class Batch:
    """A rollout cut into sequences of L = ``chunk_len`` steps, time-major.

    Actor tensors are (L, B_a, ...) with B_a = chunks * E * C, ordered
    (chunk, env, cav); critic tensors are (L, B_c, ...) with B_c = chunks * E.
    So the agents of critic sequence j are actor sequences j*C .. j*C + C-1.
    """

    actor_obs: dict[str, torch.Tensor]
    critic_state: dict[str, torch.Tensor]
    actor_h0: torch.Tensor  # (B_a, H) hidden state at each chunk start
    critic_h0: torch.Tensor  # (B_c, H)
    actor_start: torch.Tensor  # (L, B_a) bool
    critic_start: torch.Tensor  # (L, B_c) bool
    actions: torch.Tensor  # (L, B_a)
    logprobs: torch.Tensor  # (L, B_a)
    alive: torch.Tensor  # (L, B_a) float, 0 for dead/absent CAVs
    advantages: torch.Tensor  # (L, B_a) normalised over alive CAVs
    returns: torch.Tensor  # (L, B_c) unnormalised; (L, B_c, C) with per-agent values
    old_values_normalised: torch.Tensor  # (L, B_c) critic outputs at rollout time (or C)
    # A rollout collected one update behind (overlap): the learner's own log-probs before
    # this update (PPO's clip centre) and the weights pi_prox / pi_behaviour; else None.
    prox_logprobs: torch.Tensor | None = None  # (L, B_a)
    behaviour_weights: torch.Tensor | None = None  # (L, B_a)


def make_batch(
    roll: Rollout, advantages: np.ndarray, returns: np.ndarray, chunk_len: int, device: torch.device
) -> Batch:
    S, E, C = roll.actions.shape
    L = chunk_len

    def per_agent(array: np.ndarray) -> np.ndarray:  # (S, E, C, ...) -> (L, B_a, ...)
        return chunk_time_major(array.reshape(S, E * C, *array.shape[3:]), L)

    def tensor(array: np.ndarray, dtype=torch.float32) -> torch.Tensor:
        return torch.as_tensor(array, dtype=dtype, device=device)

    actor, critic = ActorObs.stack(roll.actor_obs), CriticState.stack(roll.critic_state)
    critic_arrays = critic.arrays()
    if advantages.ndim == 3:  # per-agent values: each CAV its own advantage
        adv = advantages.copy()  # (S, E, C)
        critic_arrays[AGENT_KEY] = agent_features(actor.self_state, actor.alive)  # (S, E, C, F)
    else:
        adv = np.repeat(advantages[:, :, None], C, axis=2)  # (S, E, C): team advantage per CAV
    alive_adv = adv[roll.alive]
    if alive_adv.size > 1:
        adv = (adv - alive_adv.mean()) / (alive_adv.std() + 1e-8)
    starts = roll.agent_start  # (S, E, C): episode starts and refilled slots
    return Batch(
        actor_obs=to_tensors({name: per_agent(a) for name, a in actor.arrays().items()}, device),
        critic_state=to_tensors(
            {name: chunk_time_major(array, L) for name, array in critic_arrays.items()}, device
        ),
        actor_h0=tensor(roll.actor_hidden[::L].reshape(-1, roll.actor_hidden.shape[-1])),
        critic_h0=tensor(roll.critic_hidden[::L].reshape(-1, roll.critic_hidden.shape[-1])),
        actor_start=tensor(per_agent(starts), torch.bool),
        critic_start=tensor(chunk_time_major(roll.episode_start, L), torch.bool),
        actions=tensor(per_agent(roll.actions), torch.long),
        logprobs=tensor(per_agent(roll.logprobs)),
        alive=tensor(per_agent(roll.alive)),
        advantages=tensor(per_agent(adv)),
        returns=tensor(chunk_time_major(returns, L)),
        old_values_normalised=tensor(chunk_time_major(roll.values_normalised, L)),
    )
