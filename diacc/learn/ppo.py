"""Recurrent MAPPO's algorithm, top to bottom (CleanRL's ``ppo.py``, without the run).

One update of :func:`diacc.learn.trainer.train` is, in this order:

1. :func:`collect_rollout`: ``rollout_steps`` decisions in every environment
   from a fresh reset. The actors share parameters: all CAVs of all
   environments act as one batch of E * C agents, each with its own GRU
   hidden state; a slot that a new CAV takes (``demand`` scenarios) starts
   from a zero hidden state, as at an episode start. Each step's reward is
   the team reward R the environments emit (paper eq. reward_all), at the
   softmin temperature of the schedule that this function sets in them
   (:func:`~diacc.envs.reward.temperature`, :mod:`diacc.envs.reward`).
2. :func:`rollout_values`: the centralised critic's values, after the
   rollout, one pass per chunk (one value per environment, because R is
   shared by all CAVs; ``critic_values="per_agent"`` values each CAV slot,
   :mod:`diacc.learn.models.agent_value`).
3. :func:`rollout_gae`: GAE (lambda 0.95, gamma 0.99) on de-normalised
   values, keeping termination (no bootstrap) and truncation (bootstrap) apart.
4. :func:`~diacc.learn.buffer.make_batch`: chunks of ``chunk_len`` steps,
   each replayed from the hidden state stored during the rollout.
5. :func:`add_proximal_policy` (a rollout collected one update behind,
   ``overlap``): decoupled PPO's proximal policy.
6. :func:`ppo_update`: ``epochs`` passes of clipped PPO with a clipped,
   Huber value loss (:func:`~diacc.learn.loss.minibatch_loss`). CAVs that have
   left (or were never on the road) add nothing to any actor loss (death
   masking). On CUDA (``update_path``) the same loss runs in
   :func:`~diacc.learn.static_update.static_ppo_update`: one minibatch shape,
   no host sync until the end.

:func:`learn` is steps 2-6. Actions meet PSAR as ``env.psar_actions`` says:
the proposed action's log-prob (paper), the executed one's, or sampling among
the actions PSAR would execute unchanged (``ActorObs.action_mask``,
:mod:`diacc.envs.action_mask`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from diacc.config import TrainConfig
from diacc.envs.actions import ACTION_NAMES
from diacc.envs.observation import ActorObs, CriticState
from diacc.envs.psar import RULE_NAMES, rule_counts
from diacc.envs.reward import own_reward, temperature
from diacc.envs.vector import TrainingEnvs
from diacc.learn.acting import decide
from diacc.learn.agent import ROLLOUT_DEVICE, Agent, update_path
from diacc.learn.buffer import Batch, Rollout, compute_gae, make_batch
from diacc.learn.loss import (
    LOSS_NAMES,
    NonFiniteError,
    actor_distribution,
    first_nonfinite,
    minibatch_loss,
)
from diacc.learn.loss import evaluate_batch as evaluate_batch  # where callers found it
from diacc.learn.models.agent_value import AGENT_KEY, agent_features
from diacc.learn.models.inputs import merge_leading, to_tensors
from diacc.learn.static_update import static_ppo_update
from diacc.learn.valuenorm import ValueNorm

#: Episode-counter stride per update: update u uses episode seeds u*stride, u*stride+1, ...
EPISODES_PER_UPDATE = 1000


# ----------------------------------------------------------------------------- rollout
@dataclass
class RolloutStats:
    """What a rollout saw, for logging."""

    episodes: list[dict]
    psar_counts: np.ndarray  # (4,) decisions on which each PSAR rule took effect
    decisions: int  # CAV decisions taken by alive CAVs
    restarts: int
    reward_terms: dict[str, list[float]]  # per-step means of each reward part
    seconds: float
    tau: float = float("nan")  # softmin temperature of the team rewards
    cpu_seconds: float = 0.0  # CPU time of the collecting thread (comparable under load)
    #: (A,) the actor's argmax on the decisions of living CAVs: what a greedy evaluation
    #: would pick (:mod:`diacc.learn.collapse`); actions are sampled, these are not
    greedy: np.ndarray = field(default_factory=lambda: np.zeros(len(ACTION_NAMES), np.int64))


def collect_rollout(
    agent: Agent,
    envs: TrainingEnvs,
    cfg: TrainConfig,
    update: int,
    global_step: int,
    sync: bool = True,
    values: bool = True,
) -> tuple[Rollout, np.ndarray | None, RolloutStats]:
    """Run every environment for ``rollout_steps`` decisions from a fresh reset.

    The actor runs on the agent's rollout networks (:data:`ROLLOUT_DEVICE`),
    refreshed from the learner first unless ``sync`` is False (overlap: the
    learner is being updated meanwhile). The team reward of each step is the
    one the envs emit (``Transition.team``), at the schedule's temperature at
    training step ``global_step`` (the env steps before this update, of
    ``cfg.total_steps``): set in the envs here, so tau is the same for the
    whole rollout (the envs count nothing); each ended episode's ``return`` sums them
    (an episode never spans two rollouts: every rollout starts from a reset).

    The critic does not run during the steps: values change nothing the envs
    do, so :func:`rollout_values` computes all of them after the loop in one
    pass per chunk (with ``values``, here, by the rollout critic; without, the
    learner does it, :func:`learn`). Returns the filled rollout, V(s_S) for
    bootstrapping (E,) (None without ``values``), and stats.
    """
    t0, cpu0 = time.perf_counter(), time.thread_time()
    if sync:
        agent.sync_rollout()
    actor, device = agent.rollout_actor, ROLLOUT_DEVICE
    E, C, H_a = cfg.n_envs, envs.n_cavs, actor.hidden_size
    per_agent = cfg.critic_values == "per_agent"
    roll = Rollout.allocate(cfg.rollout_steps, E, C, H_a, agent.critic.hidden_size, per_agent)
    envs.tau = temperature(global_step, cfg.total_steps, cfg.env.reward)
    actor_obs, critic_state = envs.reset(first_episode=update * EPISODES_PER_UPDATE)
    h_actor = torch.zeros(E * C, H_a, device=device)  # (E*C, H)
    start = np.ones(E, bool)
    slot_start = np.zeros((E, C), bool)  # (E, C) new CAV in the slot since the last action
    episode_return = np.zeros(E)  # (E,) team rewards of each env's current episode so far
    stats = RolloutStats([], np.zeros(len(RULE_NAMES) - 1, np.int64), 0, 0, {}, 0.0)
    stats.tau = envs.tau
    for t in range(cfg.rollout_steps):
        roll.actor_obs[t], roll.critic_state[t] = actor_obs, critic_state
        roll.episode_start[t], roll.alive[t] = start, actor_obs.alive
        roll.agent_start[t] = start[:, None] | slot_start
        roll.actor_hidden[t] = h_actor.view(E, C, H_a).cpu().numpy()
        agent_start_t = torch.as_tensor(roll.agent_start[t].reshape(-1), device=device)
        obs_t = merge_leading(to_tensors(actor_obs, device), 2)  # (E*C, ...)
        step = decide(actor, obs_t, h_actor, agent_start_t, sampled=True)  # global RNG
        h_actor, dist = step.hidden, step.policy  # (E*C, H), (E*C, 5)
        greedy = step.greedy.view(E, C).cpu().numpy()  # (E, C)
        stats.greedy += np.bincount(greedy[actor_obs.alive], minlength=len(ACTION_NAMES))
        roll.actions[t] = step.action.view(E, C).cpu().numpy()
        roll.logprobs[t] = dist.log_prob(step.action).view(E, C).cpu().numpy()

        out = envs.step(roll.actions[t])
        if cfg.env.psar_actions == "executed":  # learn from what PSAR executed
            roll.actions[t] = out.refined_action
            executed = torch.as_tensor(out.refined_action, device=device).view(-1)
            roll.logprobs[t] = dist.log_prob(executed).view(E, C).cpu().numpy()
        team = out.team
        roll.rewards[t], roll.terminated[t], roll.truncated[t] = (
            team.total,
            out.terminated,
            out.truncated,
        )
        if cfg.credit == "own":
            roll.agent_rewards[t] = own_reward(out.terms, cfg.env.reward)
            # the same CAV on the road before and after the step: its trip goes on
            goes_on = roll.alive[t] & out.actor_obs.alive & ~out.slot_start  # (E, C)
            roll.agent_ended[t] = ~goes_on
        episode_return += team.total
        for e in np.flatnonzero(out.truncated):  # bootstrap from where the episode was cut
            final_actor = out.final_actor_obs[e]
            if final_actor is None:  # a simulator crash: the CAVs' last features are gone
                final_actor = actor_obs.unbatched(e)
            roll.cut_states.append((t, int(e), out.final_critic_state[e], final_actor))
        stats.episodes += [
            {"return": float(episode_return[e]), **ep} for e, ep in out.episodes.items()
        ]
        stats.psar_counts += rule_counts(out.psar_rule_mask[roll.alive[t]])
        stats.decisions += int(roll.alive[t].sum())
        stats.restarts += out.restarts
        reported = ~out.crashed  # envs whose simulator did not crash in this step
        if reported.any():
            terms = {
                "ego_softmin": team.ego_softmin[reported],
                **out.reward_terms,
                "tau": np.full(int(reported.sum()), stats.tau),
            }
            for key, values_ in terms.items():
                stats.reward_terms.setdefault(key, []).append(float(values_.mean()))
        actor_obs, critic_state = out.actor_obs, out.critic_state
        start = out.terminated | out.truncated
        episode_return[start] = 0.0
        slot_start = out.slot_start
    roll.next_actor_obs, roll.next_critic_state = actor_obs, critic_state
    next_value = None
    if values:
        next_value = rollout_values(
            agent.rollout_critic, agent.rollout_value_norm, roll, cfg, device
        )
    stats.seconds, stats.cpu_seconds = time.perf_counter() - t0, time.thread_time() - cpu0
    return roll, next_value, stats


# ----------------------------------------------------------------------------- values and GAE
@torch.no_grad()
def rollout_values(critic, value_norm: ValueNorm, roll: Rollout, cfg: TrainConfig, device):
    """The critic's values of a collected rollout; returns V(s_S) (E,) for bootstrapping.

    Fills ``roll.values`` (de-normalised, for GAE), ``values_normalised`` (the
    value-clip centre), ``critic_hidden`` (the state *before* each step, the
    update's chunk starts) and ``final_values`` (episodes cut by the time
    limit). The critic replays the rollout one chunk of ``chunk_len`` steps at a
    time, carrying its hidden state: the same recursion as stepping along with
    the envs, in S / L forwards instead of S, and with memory bounded by a
    chunk (a demand critic sees hundreds of vehicles per state).
    """
    per_agent = cfg.critic_values == "per_agent"
    S, E = roll.episode_start.shape
    L = cfg.chunk_len
    hidden = torch.zeros(E, critic.hidden_size, device=device)  # (E, H)
    after = []  # (L, E, H) states after each step, chunk by chunk
    for t0 in range(0, S, L):
        steps = slice(t0, t0 + L)
        inputs = critic_inputs(
            CriticState.stack(roll.critic_state[steps]),
            ActorObs.stack(roll.actor_obs[steps]),
            per_agent,
            device,
        )  # (L, E, ...)
        roll.critic_hidden[t0] = hidden.cpu().numpy()
        value, states = critic.forward_sequence(
            inputs, hidden, torch.as_tensor(roll.episode_start[steps], device=device), True
        )  # (L, E) or (L, E, C); (L, E, H)
        roll.values_normalised[steps] = value.cpu().numpy()
        roll.values[steps] = value_norm.denormalize(value).cpu().numpy()
        hidden = states[-1]
        after.append(states)
    after_t = torch.cat(after)  # (S, E, H)
    roll.critic_hidden[1:] = after_t[:-1].cpu().numpy()
    if roll.cut_states:  # V of each truncated episode's last state, from the state after t
        ts, es, finals, actors = zip(*roll.cut_states, strict=True)
        v_final, _ = critic(
            critic_inputs(CriticState.stack(finals), ActorObs.stack(actors), per_agent, device),
            after_t[list(ts), list(es)],
            torch.zeros(len(ts), dtype=torch.bool, device=device),
        )
        roll.final_values[list(ts), list(es)] = value_norm.denormalize(v_final).cpu().numpy()
    last_start = roll.terminated[-1] | roll.truncated[-1]  # (E,) a new episode at s_S
    next_value, _ = critic(
        critic_inputs(roll.next_critic_state, roll.next_actor_obs, per_agent, device),
        hidden,
        torch.as_tensor(last_start, device=device),
    )
    return value_norm.denormalize(next_value).cpu().numpy()


def rollout_gae(roll: Rollout, next_value: np.ndarray, cfg: TrainConfig):
    """Advantages and returns (S, E) of a rollout (see :func:`compute_gae`).

    With per-agent values (S, E, C) the team reward and episode flags are
    broadcast over the CAV slots: GAE per agent on the shared reward; with
    ``credit = "own"`` each CAV's own reward instead, and its trip's end
    (arrival, crash) terminates its returns as the episode's end does.
    """
    shape = roll.values.shape

    def per_value(array: np.ndarray) -> np.ndarray:  # (S, E) -> shape of the values
        return np.broadcast_to(array.reshape(array.shape + (1,) * (len(shape) - 2)), shape)

    rewards, terminated = per_value(roll.rewards), per_value(roll.terminated)
    if cfg.credit == "own":
        rewards, terminated = roll.agent_rewards, terminated | roll.agent_ended
    return compute_gae(
        rewards,
        roll.values,
        next_value,
        terminated,
        per_value(roll.truncated),
        roll.final_values,
        cfg.gamma,
        cfg.gae_lambda,
    )


def critic_inputs(critic_state, actor_obs, per_agent: bool, device) -> dict[str, torch.Tensor]:
    """The critic's input: its state, and with per-agent values each slot's own features."""
    tensors = to_tensors(critic_state, device)
    if per_agent:
        features = agent_features(actor_obs.self_state, actor_obs.alive)  # (E, C, F)
        tensors[AGENT_KEY] = torch.as_tensor(features, device=device)
    return tensors


# ----------------------------------------------------------------------------- replay
#: Cap of the importance weight pi_prox / pi_behaviour of a lagged rollout: one
#: update apart the two policies barely differ (approx. KL < 0.01), so the cap only
#: guards against an action the behaviour policy took with a tiny probability.
MAX_BEHAVIOUR_WEIGHT = 2.0


@torch.no_grad()
def add_proximal_policy(agent: Agent, batch: Batch, cfg: TrainConfig, n_cavs: int) -> None:
    """Make a lagged rollout's batch (overlap) train like a fresh one.

    A rollout collected beside the previous update acts with the parameters from
    before that update. PPO's clip around *those* log-probs starts the update
    already off-centre and cuts its steps short (docs/benchmarks, "Training
    throughput II" and "III", has the measurements). The decoupled PPO objective
    (Hilton et al. 2022, "Batch size-invariance for policy optimization") clips
    around the learner's own policy before this update (``prox_logprobs``) and
    corrects for the behaviour policy with the weight pi_prox / pi_behaviour
    (capped at :data:`MAX_BEHAVIOUR_WEIGHT`). One forward pass of the actor over
    the rollout, minibatch by minibatch.
    """
    autocast = torch.autocast(batch.returns.device.type, torch.bfloat16, enabled=cfg.update_bf16)
    prox = torch.empty_like(batch.logprobs)  # (L, B_a)
    n_sequences = batch.critic_h0.shape[0]
    with autocast:
        for envs_idx in torch.arange(n_sequences, device=prox.device).chunk(cfg.minibatches):
            dist, agents_idx = actor_distribution(agent, batch, envs_idx, n_cavs)
            prox[:, agents_idx] = dist.log_prob(batch.actions[:, agents_idx])
    batch.prox_logprobs = prox
    batch.behaviour_weights = (prox - batch.logprobs).exp().clamp(max=MAX_BEHAVIOUR_WEIGHT)


# ----------------------------------------------------------------------------- PPO update
def ppo_update(
    agent: Agent,
    batch: Batch,
    cfg: TrainConfig,
    n_cavs: int,
    generator: torch.Generator | None = None,
) -> dict[str, float]:
    """``epochs`` passes of clipped PPO over the batch; returns mean diagnostics.

    With ``cfg.update_bf16`` the network forwards run under bf16 autocast
    (weights, optimiser and losses stay fp32), on the CPU as on CUDA.
    Minibatches are drawn from ``generator`` (default: torch's global one);
    an update running beside a rollout needs its own, or the two threads'
    draws would interleave differently from run to run.
    """
    agent.value_norm.update(batch.returns)
    # Clip around what the critic predicted during the rollout (MAPPO,
    # ``old_values_normalised``): re-normalising the de-normalised values with the
    # statistics just updated would move the centre.
    returns_n = agent.value_norm.normalize(batch.returns)
    stats: dict[str, list[float]] = {k: [] for k in LOSS_NAMES}
    n_sequences = batch.critic_h0.shape[0]
    for epoch in range(cfg.epochs):
        # Minibatches of whole (chunk, env) sequences keep each env's CAVs with its critic.
        for minibatch, envs_idx in enumerate(
            torch.randperm(n_sequences, device=batch.returns.device, generator=generator).chunk(
                cfg.minibatches
            )
        ):
            parts = minibatch_loss(agent, batch, returns_n, envs_idx, cfg, n_cavs)
            where = f"epoch {epoch + 1}, minibatch {minibatch + 1}"
            for name, value in (
                ("policy_loss", parts.policy_loss),
                ("value_loss", parts.value_loss),
                ("entropy", parts.entropy),
                ("loss", parts.loss),
            ):
                if not torch.isfinite(value):
                    raise NonFiniteError(f"non-finite {name} ({value.item()}) in {where}")
            agent.optimizer.zero_grad()
            parts.loss.backward()
            for part, net in (("actor", agent.actor), ("critic", agent.critic)):
                norm = torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.max_grad_norm)
                if not torch.isfinite(norm):
                    bad = first_nonfinite(net, part, grad=True)
                    raise NonFiniteError(f"non-finite gradient of {bad} in {where}")
            agent.optimizer.step()
            for name, value in zip(LOSS_NAMES, parts.stacked().tolist(), strict=True):
                stats[name].append(value)
    for part, net in (("actor", agent.actor), ("critic", agent.critic)):
        bad = first_nonfinite(net, part)
        if bad is not None:
            raise NonFiniteError(f"non-finite parameter {bad} after the optimiser step")
    return {k: float(np.mean(v)) for k, v in stats.items()}


def learn(
    agent: Agent,
    roll: Rollout,
    next_value: np.ndarray | None,
    cfg: TrainConfig,
    device: torch.device,
    n_cavs: int,
    generator: torch.Generator | None = None,
    lagged: bool = False,
) -> tuple[np.ndarray, dict[str, float]]:
    """Values, GAE, batching and the PPO update of one rollout; returns (returns (S, E), losses).

    ``next_value`` None: the rollout's values are computed here, by the learner's
    critic (:func:`rollout_values`), so that a rollout collected beside the previous
    update (``lagged``, overlap) is valued by the critic that this update trains;
    its policy loss then uses :func:`add_proximal_policy`. ``losses`` also holds
    ``learner_s`` and ``learner_cpu_s``, the wall and CPU seconds this took (the
    learner's share of an update, logged for ``diacc bench --training``).
    """
    t0, cpu0 = time.perf_counter(), time.thread_time()
    if next_value is None:
        next_value = rollout_values(agent.critic, agent.value_norm, roll, cfg, device)
    advantages, returns = rollout_gae(roll, next_value, cfg)
    for name, array in (("reward", roll.rewards), ("returns", returns)):
        if not np.isfinite(array).all():
            raise NonFiniteError(f"non-finite {name} in the rollout")
    batch = make_batch(roll, advantages, returns, cfg.chunk_len, device)
    if lagged:
        add_proximal_policy(agent, batch, cfg, n_cavs)
    if update_path(cfg, device) == "static":
        losses = static_ppo_update(agent, batch, cfg, n_cavs, generator)
    else:
        losses = ppo_update(agent, batch, cfg, n_cavs, generator)
    seconds = {"learner_s": time.perf_counter() - t0, "learner_cpu_s": time.thread_time() - cpu0}
    return returns, {**losses, **seconds}
