"""Recurrent MAPPO for the bottleneck, readable top to bottom (CleanRL style).

One update = one rollout of ``rollout_steps`` decisions in every environment,
then ``epochs`` passes of PPO over it:

* **Actors** share parameters. All CAVs of all environments act as one batch
  of E * C agents; each has its own GRU hidden state.
* **Critic** is centralised: one value per environment from the critic state,
  because the team reward R_t is shared by all CAVs (paper eq. reward_all);
  ``critic_values="per_agent"`` values each CAV slot instead
  (:mod:`diacc.learn.models.agent_value`), with GAE per agent.
* **Actions** meet PSAR as ``env.psar_actions`` says: the proposed action's
  log-prob (paper), the executed one's, or sampling among the actions PSAR
  would execute unchanged (``ActorObs.action_mask``, :mod:`diacc.envs.action_mask`).
* **Team reward** (paper eq. reward_all): the environments return its
  parts that need no temperature; the rollout aggregates them with the
  softmin at the temperature annealed for this update
  (:func:`~diacc.envs.reward.temperature`, :func:`~diacc.envs.reward.team_reward`),
  and sums them into each episode's return.
* **GAE** (lambda 0.95, gamma 0.99) on de-normalised values, keeping
  termination (no bootstrap) and truncation (bootstrap) apart.
* **Recurrent training** on chunks of ``chunk_len`` steps, each started from
  the hidden state stored during the rollout, with hidden states zeroed at
  episode starts inside a chunk.
* **Death masking**: CAVs that have left (or were never on the road) add
  nothing to any actor loss.
* **Agent slots refill** (``demand`` scenarios, :mod:`diacc.envs.env`): a slot
  that a new CAV takes starts from a zero actor hidden state, in the rollout
  and in the chunked replay (``agent_start``), as at an episode start. The
  advantage is the team's, per environment, so the previous occupant needs no
  GAE cut of its own: its steps end where its slot went dead (masked).
* Every update starts all environments afresh with seeds derived from
  (run seed, env, update); with the RNG states in the checkpoint this makes
  ``--resume`` reproduce an uninterrupted run exactly.
* **Overlap** (``overlap = true``, off by default): the next rollout is
  collected on the main thread while a second thread runs the PPO update,
  so both cores work. That rollout acts with the parameters from *before*
  the update (a one-update policy lag); PPO's ratios are taken against the
  stored log-probabilities of that behaviour policy, so its importance
  weighting and clipping apply as they are. See :func:`_train_loop`.
"""

from __future__ import annotations

import copy
import functools
import json
import random
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.tensorboard import SummaryWriter

from diacc.config import TrainConfig, flatten_config, validate
from diacc.console import TrainProgress
from diacc.envs.action_mask import masked_logits
from diacc.envs.observation import ObservationSpec, check_road, stack, unstack
from diacc.envs.psar import RULE_NAMES, rule_counts
from diacc.envs.reward import team_reward, temperature
from diacc.envs.vector import make_vector_env
from diacc.errors import DiaccError
from diacc.fileio import atomic_write, open_append
from diacc.learn.agent import Agent
from diacc.learn.buffer import Rollout, compute_gae
from diacc.learn.checkpoint import (
    CheckpointError,
    config_from_checkpoint,
    init_networks,
    load_checkpoint,
    restore,
    save_checkpoint,
    set_rng_state,
)
from diacc.learn.models.agent_value import AGENT_KEY, AgentValueCritic, agent_features
from diacc.learn.models.inputs import to_tensors
from diacc.learn.models.registry import build_networks
from diacc.learn.progress import check_agrees as check_progress
from diacc.learn.progress import keep_until as keep_progress_until
from diacc.learn.progress import read_rows as progress_rows
from diacc.learn.valuenorm import ValueNorm
from diacc.runlog import claim_run_dir, config_digest, locked_dir, log, run_log
from diacc.sim.maps import load_map
from diacc.sim.scenario import draw_population
from diacc.threads import set_torch_threads

#: Episode-counter stride per update: update u uses episode seeds u*stride, u*stride+1, ...
EPISODES_PER_UPDATE = 1000


def resolve_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise TrainingError(
            "--device cuda requested but this machine has no CUDA device "
            f"(torch {torch.__version__}); use --device cpu or auto"
        )
    return torch.device(name)


def device_here(name: str) -> str:
    """The device ``name`` means on this machine (``auto`` -> ``cuda`` or ``cpu``), without
    :func:`resolve_device`'s check: a resume compares what the update ran on, so that a
    run saved with ``device`` ``cpu`` continues under ``auto`` on a machine without CUDA
    (the default of ``sweep`` and ``reproduce`` was ``cpu`` before it became ``auto``)."""
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


def flatten_agents(container, n_axes: int = 2):
    """Merge the first ``n_axes`` axes of every field: (E, C, ...) -> (E*C, ...)."""
    cls = type(container)
    return cls(
        **{
            f.name: (lambda a: a.reshape(-1, *a.shape[n_axes:]))(getattr(container, f.name))
            for f in fields(cls)
        }
    )


def chunk_time_major(arrays: np.ndarray, chunk_len: int) -> np.ndarray:
    """(S, B, ...) -> (L, S/L * B, ...): sequences of L steps, one per (chunk, b)."""
    steps, batch = arrays.shape[:2]
    out = arrays.reshape(steps // chunk_len, chunk_len, batch, *arrays.shape[2:])
    return out.swapaxes(0, 1).reshape(chunk_len, (steps // chunk_len) * batch, *arrays.shape[2:])


def explained_variance(pred: np.ndarray, target: np.ndarray) -> float:
    var = np.var(target)
    return float("nan") if var == 0 else float(1 - np.var(target - pred) / var)


#: Where rollout forwards run: one small batch per decision step, between CPU-bound
#: environment steps, so a GPU would only add transfers and kernel launches.
ROLLOUT_DEVICE = torch.device("cpu")


def make_agent(cfg: TrainConfig, device: torch.device) -> Agent:
    """The networks of ``cfg.variant`` with the learner on ``device`` (rollouts on the CPU)."""
    actor, critic = build_networks(cfg.variant, cfg.model, ObservationSpec.from_config(cfg.env.obs))
    if cfg.critic_values == "per_agent":
        critic = AgentValueCritic(critic, cfg.model)
    value_norm = ValueNorm()
    extras = {}
    # Separate rollout networks: on another device, or when rollouts run beside the update.
    if device != ROLLOUT_DEVICE or cfg.overlap:
        extras = {
            "rollout_actor": copy.deepcopy(actor),
            "rollout_critic": copy.deepcopy(critic),
            "rollout_value_norm": copy.deepcopy(value_norm),
        }
    actor, critic, value_norm = actor.to(device), critic.to(device), value_norm.to(device)
    params = list(actor.parameters()) + list(critic.parameters())
    # fused: one kernel per parameter tensor instead of about ten (docs/benchmarks). A
    # checkpoint restores the flag it was saved with, so old runs resume as they ran.
    fused = device.type in ("cpu", "cuda")
    optimizer = torch.optim.Adam(params, lr=cfg.lr, eps=cfg.adam_eps, fused=fused)
    if cfg.update_compile:
        extras["actor_sequence"] = torch.compile(actor.forward_sequence)
        extras["critic_sequence"] = torch.compile(critic.forward_sequence)
    return Agent(actor, critic, value_norm, optimizer, **extras)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


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
    cpu_seconds: float = 0.0  # CPU time of the collecting thread (comparable under load)


def collect_rollout(
    agent: Agent,
    envs,
    cfg: TrainConfig,
    update: int,
    tau: float,
    sync: bool = True,
    values: bool = True,
) -> tuple[Rollout, np.ndarray | None, RolloutStats]:
    """Run every environment for ``rollout_steps`` decisions from a fresh reset.

    The actor runs on the agent's rollout networks (:data:`ROLLOUT_DEVICE`),
    refreshed from the learner first unless ``sync`` is False (overlap: the
    learner is being updated meanwhile). The team reward of each step is
    :func:`~diacc.envs.reward.team_reward` of the envs' reward terms at the
    softmin temperature ``tau`` (:func:`~diacc.envs.reward.temperature` of the
    update); each ended episode's ``return`` sums them (an episode never spans
    two rollouts: every rollout starts from a reset).

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
    actor_obs, critic_state = envs.reset(first_episode=update * EPISODES_PER_UPDATE)
    h_actor = torch.zeros(E * C, H_a, device=device)  # (E*C, H)
    start = np.ones(E, bool)
    slot_start = np.zeros((E, C), bool)  # (E, C) new CAV in the slot since the last action
    episode_return = np.zeros(E)  # (E,) team rewards of each env's current episode so far
    stats = RolloutStats([], np.zeros(len(RULE_NAMES) - 1, np.int64), 0, 0, {}, 0.0)
    for t in range(cfg.rollout_steps):
        roll.actor_obs[t], roll.critic_state[t] = actor_obs, critic_state
        roll.episode_start[t], roll.alive[t] = start, actor_obs.alive
        roll.agent_start[t] = start[:, None] | slot_start
        roll.actor_hidden[t] = h_actor.view(E, C, H_a).cpu().numpy()
        with torch.no_grad():
            agent_start_t = torch.as_tensor(roll.agent_start[t].reshape(-1), device=device)
            obs_t = to_tensors(flatten_agents(actor_obs), device)
            logits, h_actor = actor(obs_t, h_actor, agent_start_t)
            # All True unless env.psar_actions = "masked" (then a no-op: same numbers).
            logits = masked_logits(logits, obs_t["action_mask"])  # (E*C, 5)
            dist = torch.distributions.Categorical(logits=logits)
            action = dist.sample()  # (E*C,)
        roll.actions[t] = action.view(E, C).cpu().numpy()
        roll.logprobs[t] = dist.log_prob(action).view(E, C).cpu().numpy()

        out = envs.step(roll.actions[t])
        if cfg.env.psar_actions == "executed":  # learn from what PSAR executed
            roll.actions[t] = out.refined_action
            executed = torch.as_tensor(out.refined_action, device=device).view(-1)
            roll.logprobs[t] = dist.log_prob(executed).view(E, C).cpu().numpy()
        team = team_reward(
            out.ego, out.alive, out.global_reward, out.completion, out.delay, tau, cfg.env.reward
        )
        roll.rewards[t], roll.terminated[t], roll.truncated[t] = (
            team.total,
            out.terminated,
            out.truncated,
        )
        episode_return += team.total
        for e in np.flatnonzero(out.truncated):  # bootstrap from where the episode was cut
            final_actor = out.final_actor_obs[e]
            if final_actor is None:  # a simulator crash: the CAVs' last features are gone
                final_actor = unstack(actor_obs, e)
            roll.cut_states.append((t, int(e), out.final_critic_state[e], final_actor))
        stats.episodes += [
            {"return": float(episode_return[e]), **ep} for e, ep in out.episodes.items()
        ]
        stats.psar_counts += rule_counts(out.psar_rule_mask[roll.alive[t]])
        stats.decisions += int(roll.alive[t].sum())
        stats.restarts += out.restarts
        reported = ~out.restarted  # envs whose simulator did not crash in this step
        if reported.any():
            terms = {
                "ego_softmin": team.ego_softmin[reported],
                **out.reward_terms,
                "tau": np.full(int(reported.sum()), tau),
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
            stack(roll.critic_state[steps]), stack(roll.actor_obs[steps]), per_agent, device
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
            critic_inputs(stack(list(finals)), stack(list(actors)), per_agent, device),
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
    broadcast over the CAV slots: GAE per agent on the shared reward.
    """
    shape = roll.values.shape

    def per_value(array: np.ndarray) -> np.ndarray:  # (S, E) -> shape of the values
        return np.broadcast_to(array.reshape(array.shape + (1,) * (len(shape) - 2)), shape)

    return compute_gae(
        per_value(roll.rewards),
        roll.values,
        next_value,
        per_value(roll.terminated),
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


# ----------------------------------------------------------------------------- batch
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

    actor, critic = stack(roll.actor_obs), stack(roll.critic_state)
    critic_arrays = {f.name: getattr(critic, f.name) for f in fields(critic)}
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
        actor_obs=to_tensors(
            {f.name: per_agent(getattr(actor, f.name)) for f in fields(actor)}, device
        ),
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


def evaluate_batch(agent: Agent, batch: Batch, envs_idx: torch.Tensor, n_cavs: int):
    """Replay critic sequences ``envs_idx`` and their CAVs' actor sequences.

    Returns (new log-probs (L, b_a), entropy (L, b_a), normalised values (L, b_c),
    actor sequence indices b_a).
    """
    dist, agents_idx = actor_distribution(agent, batch, envs_idx, n_cavs)
    values, _ = agent.replay_critic(
        {k: v[:, envs_idx] for k, v in batch.critic_state.items()},
        batch.critic_h0[envs_idx],
        batch.critic_start[:, envs_idx],
    )
    # float(): under bf16 autocast the networks return bf16; losses are taken in fp32.
    return dist.log_prob(batch.actions[:, agents_idx]), dist.entropy(), values.float(), agents_idx


def actor_distribution(agent: Agent, batch: Batch, envs_idx: torch.Tensor, n_cavs: int):
    """The learner actor's action distribution (L, b_a, 5) on the CAVs of critic
    sequences ``envs_idx``, and their actor sequence indices b_a."""
    agents_idx = (
        envs_idx[:, None] * n_cavs + torch.arange(n_cavs, device=envs_idx.device)
    ).reshape(-1)
    logits, _ = agent.replay_actor(
        {k: v[:, agents_idx] for k, v in batch.actor_obs.items()},
        batch.actor_h0[agents_idx],
        batch.actor_start[:, agents_idx],
    )
    logits = masked_logits(logits.float(), batch.actor_obs["action_mask"][:, agents_idx])
    return torch.distributions.Categorical(logits=logits), agents_idx


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
    autocast = functools.partial(
        torch.autocast, batch.returns.device.type, torch.bfloat16, enabled=cfg.update_bf16
    )
    agent.value_norm.update(batch.returns)
    returns_n = agent.value_norm.normalize(batch.returns)
    # Clip around what the critic predicted during the rollout (MAPPO): re-normalising
    # the de-normalised values with the statistics just updated would move the centre.
    old_values_n = batch.old_values_normalised
    stats: dict[str, list[float]] = {
        k: [] for k in ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac")
    }
    n_sequences = batch.critic_h0.shape[0]
    for epoch in range(cfg.epochs):
        # Minibatches of whole (chunk, env) sequences keep each env's CAVs with its critic.
        for minibatch, envs_idx in enumerate(
            torch.randperm(n_sequences, device=batch.returns.device, generator=generator).chunk(
                cfg.minibatches
            )
        ):
            with autocast():
                logprob, entropy, value, agents_idx = evaluate_batch(agent, batch, envs_idx, n_cavs)
            mask = batch.alive[:, agents_idx]  # (L, b_a): dead CAVs add nothing
            n_alive = mask.sum().clamp(min=1.0)
            centre = batch.logprobs if batch.prox_logprobs is None else batch.prox_logprobs
            log_ratio = logprob - centre[:, agents_idx]
            ratio = log_ratio.exp()
            adv = batch.advantages[:, agents_idx]
            surrogate = torch.min(ratio * adv, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv)
            if batch.behaviour_weights is not None:  # a lagged rollout (add_proximal_policy)
                surrogate = surrogate * batch.behaviour_weights[:, agents_idx]
            policy_loss = -(surrogate * mask).sum() / n_alive
            entropy_mean = (entropy * mask).sum() / n_alive
            old_v, target = old_values_n[:, envs_idx], returns_n[:, envs_idx]
            v_clipped = old_v + (value - old_v).clamp(-cfg.clip, cfg.clip)
            value_loss = torch.max(
                F.huber_loss(value, target, delta=cfg.huber_delta, reduction="none"),
                F.huber_loss(v_clipped, target, delta=cfg.huber_delta, reduction="none"),
            ).mean()
            loss = policy_loss - cfg.entropy_coef * entropy_mean + cfg.value_coef * value_loss
            where = f"epoch {epoch + 1}, minibatch {minibatch + 1}"
            for name, value in (
                ("policy_loss", policy_loss),
                ("value_loss", value_loss),
                ("entropy", entropy_mean),
                ("loss", loss),
            ):
                if not torch.isfinite(value):
                    raise NonFiniteError(f"non-finite {name} ({value.item()}) in {where}")
            agent.optimizer.zero_grad()
            loss.backward()
            for part, net in (("actor", agent.actor), ("critic", agent.critic)):
                norm = torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.max_grad_norm)
                if not torch.isfinite(norm):
                    bad = _first_nonfinite(net, part, grad=True)
                    raise NonFiniteError(f"non-finite gradient of {bad} in {where}")
            agent.optimizer.step()
            with torch.no_grad():
                stats["policy_loss"].append(policy_loss.item())
                stats["value_loss"].append(value_loss.item())
                stats["entropy"].append(entropy_mean.item())
                stats["approx_kl"].append(
                    ((((ratio - 1) - log_ratio) * mask).sum() / n_alive).item()
                )
                stats["clipfrac"].append(
                    ((((ratio - 1).abs() > cfg.clip).float() * mask).sum() / n_alive).item()
                )
    for part, net in (("actor", agent.actor), ("critic", agent.critic)):
        bad = _first_nonfinite(net, part)
        if bad is not None:
            raise NonFiniteError(f"non-finite parameter {bad} after the optimiser step")
    return {k: float(np.mean(v)) for k, v in stats.items()}


class NonFiniteError(DiaccError, RuntimeError):
    """A loss, gradient or parameter became NaN/inf; the update must not be kept."""


def _first_nonfinite(net: torch.nn.Module, part: str, grad: bool = False) -> str | None:
    """First parameter (or gradient) holding NaN/inf, by name (``critic.head.weight``)."""
    for name, param in net.named_parameters():
        tensor = param.grad if grad else param
        if tensor is not None and not torch.isfinite(tensor).all():
            return f"{part}.{name}"
    return None if not grad else f"{part} (norm)"


# ----------------------------------------------------------------------------- training
class TrainingError(DiaccError, RuntimeError):
    """Training cannot go on (a non-finite update, a missing device); the message is one line."""


class TrainingInterrupted(KeyboardInterrupt):
    """SIGINT/SIGTERM stopped the run at an update boundary, after saving a checkpoint."""

    def __init__(self, signum: int, update: int, checkpoint: Path) -> None:
        self.signum, self.update, self.checkpoint = signum, update, checkpoint
        super().__init__(
            f"interrupted by {signal.Signals(signum).name} after update {update}; "
            f"checkpoint saved to {checkpoint} (continue with --resume)"
        )


#: Config fields a resumed run may change: the step budget, and where the run lives.
RESUME_FREE_FIELDS = ("total_steps", "run_dir")


def check_resume_config(
    saved: dict, cfg: TrainConfig, path: Path, allow_change: bool = False
) -> list[str]:
    """Fields (other than :data:`RESUME_FREE_FIELDS`) where ``cfg`` differs from the checkpoint's.

    ``device`` counts as what it means here (:func:`device_here`). Raises
    :class:`CheckpointError` naming the first one unless ``allow_change``.
    """
    old, new = flatten_config(saved), flatten_config(asdict(cfg))
    for flat in (old, new):
        if "device" in flat:
            flat["device"] = device_here(flat["device"])
    changed = [
        k
        for k in sorted(set(old) | set(new), key=lambda k: (k.count("."), k))  # top level first
        if k not in RESUME_FREE_FIELDS and old.get(k) != new.get(k)
    ]
    if changed and not allow_change:
        key = changed[0]
        raise CheckpointError(
            f"checkpoint {path} was trained with {key} {old.get(key)!r}, not {new.get(key)!r}; "
            "--resume may change only --steps (pass --allow-config-change to override)"
        )
    return changed


class StoppedAtOnce(KeyboardInterrupt):
    """A second SIGINT/SIGTERM: training stopped mid-update; ``signum`` sets the exit status."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum

    def __str__(self) -> str:
        return f"stopped at once by a second {signal.Signals(self.signum).name}"


class _StopOnSignal:
    """SIGINT/SIGTERM/SIGHUP set :attr:`signum`; the loop stops at the next update boundary.

    A second signal stops at once (:class:`StoppedAtOnce`), keeping the last checkpoint.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)

    def __init__(self) -> None:
        self.signum: int | None = None
        self.previous: dict = {}

    def __enter__(self) -> _StopOnSignal:
        if threading.current_thread() is threading.main_thread():
            self.previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc) -> None:
        for s, handler in self.previous.items():
            signal.signal(s, handler)

    def _handle(self, signum: int, frame) -> None:
        if self.signum is not None:
            raise StoppedAtOnce(signum)
        self.signum = signum
        log.warning(
            "%s received: saving a checkpoint after the current update (again to stop now)",
            signal.Signals(signum).name,
        )


def check_config(cfg: TrainConfig) -> None:
    """One-line errors for a config :func:`train` cannot run, before anything is printed or written.

    The first vehicles' placement checks that the scenario fits the map (it used
    to fail in the first reset, after config.json and tb/ existed).
    """
    validate(cfg)
    for road_map in (cfg.env.map, *cfg.extra_maps):
        road = load_map(road_map)
        check_road(road)  # the observation's road and lane tables hold it
        draw_population(cfg.env.scenario, road, cfg.seed)


def train(
    cfg: TrainConfig,
    resume: bool = False,
    progress: bool = True,
    stop_after_updates: int | None = None,
    allow_config_change: bool = False,
    overwrite: bool = False,
) -> Path:
    """Train ``cfg.variant``; returns the run directory (config, checkpoints, logs).

    ``stop_after_updates`` ends the run early (as if interrupted) after that
    many updates, with a checkpoint; ``resume=True`` continues from it, with
    the same config but for the step budget (unless ``allow_config_change``),
    and cuts ``progress.jsonl`` and TensorBoard back to the checkpoint.
    Nothing is written before the config (and checkpoint) passed their checks.
    The run directory is locked while training; one that holds a run is
    refused unless ``resume`` (continue it) or ``overwrite`` (replace it).
    """
    check_config(cfg)
    device = resolve_device(cfg.device)
    run_dir = Path(cfg.run_dir)
    with locked_dir(run_dir, "train"):
        claim_run_dir(run_dir, resume, overwrite)
        return _start(
            cfg, run_dir, device, resume, progress, stop_after_updates, allow_config_change
        )


def _start(
    cfg: TrainConfig,
    run_dir: Path,
    device: torch.device,
    resume: bool,
    progress: bool,
    stop_after_updates: int | None,
    allow_config_change: bool,
) -> Path:
    """:func:`train` once the inputs are checked and ``run_dir`` is locked and claimed."""
    ckpt_path = run_dir / "checkpoint.pt"
    seed_everything(cfg.seed)
    set_torch_threads(cfg.torch_threads)
    agent = make_agent(cfg, device)
    steps_per_update = cfg.rollout_steps * cfg.n_envs
    n_updates = max(1, cfg.total_steps // steps_per_update)
    first_update, global_step, changed, rows = 0, 0, [], None
    progress_path = run_dir / "progress.jsonl"
    if resume:
        payload = load_checkpoint(ckpt_path, device)
        saved = asdict(config_from_checkpoint(payload))
        changed = check_resume_config(saved, cfg, ckpt_path, allow_config_change)
        restore(agent, payload, cfg, ckpt_path)
        first_update, global_step = payload["update"], payload["global_step"]
        if progress_path.exists():  # checked before anything is written
            rows = progress_rows(progress_path)
            check_progress(rows, progress_path, first_update, global_step)
        set_rng_state(payload["rng"])
    elif cfg.init_from:
        source = init_networks(agent, Path(cfg.init_from), cfg)
    with run_log(run_dir / "train.log"):
        if cfg.init_from and not resume:
            log.info(
                "networks from %s (%s, trained on %s %s for %d steps); optimiser fresh",
                cfg.init_from,
                source["variant"],
                source["backend"],
                source["map"],
                source["global_step"],
            )
        if changed:
            log.warning("resuming %s with changed config fields: %s", run_dir, ", ".join(changed))
        if rows is not None:
            keep_progress_until(progress_path, rows, first_update)
        atomic_write(run_dir / "config.json", json.dumps(asdict(cfg), indent=2, default=str))
        last_update = (
            n_updates
            if stop_after_updates is None
            else min(n_updates, first_update + stop_after_updates)
        )
        return _train_loop(
            agent, cfg, run_dir, device, first_update, last_update, n_updates, global_step, progress
        )


def _train_loop(
    agent: Agent,
    cfg: TrainConfig,
    run_dir: Path,
    device: torch.device,
    first_update: int,
    last_update: int,
    n_updates: int,
    global_step: int,
    progress: bool,
) -> Path:
    ckpt_path = run_dir / "checkpoint.pt"
    steps_per_update = cfg.rollout_steps * cfg.n_envs
    saved_update = first_update if first_update else None
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed, cfg.vector, cfg.extra_maps)
    # purge_step: TensorBoard drops the events a resumed run logged after its checkpoint.
    # It reads event files in name order, and names start with the creation second:
    # a resumed file must not share its second with the interrupted run's last file.
    if first_update:
        _wait_past_event_files(run_dir / "tb")
    writer = SummaryWriter(
        str(run_dir / "tb"), purge_step=global_step + 1 if first_update else None
    )
    bar = TrainProgress(n_updates * steps_per_update, global_step, f"train {cfg.variant}", progress)
    log.info(
        "start: %s in %s, updates %d-%d of %d (%d env steps each), config %s",
        cfg.variant,
        run_dir,
        first_update + 1,
        last_update,
        n_updates,
        steps_per_update,
        config_digest(cfg),
    )
    started_s = time.perf_counter()
    try:
        with _StopOnSignal() as stop:
            # The next update's rollout when overlap collected it beside the learner
            # (lagged: one update behind), else None.
            collected, lagged = None, False
            for update in range(first_update, last_update):
                t0 = time.perf_counter()
                if cfg.lr_decay:
                    for group in agent.optimizer.param_groups:
                        group["lr"] = cfg.lr * (1.0 - update / n_updates)
                tau = temperature(global_step, cfg.total_steps, cfg.env.reward)
                if collected is None:
                    collected, lagged = (
                        collect_rollout(agent, envs, cfg, update, tau, values=False),
                        False,
                    )
                roll, next_value, rollout = collected
                if rollout.restarts:
                    log.warning(
                        "update %d: %d simulator restart(s) in the rollout; episodes cut",
                        update + 1,
                        rollout.restarts,
                    )
                # Prefetch the next rollout during this update, except before a checkpoint:
                # a resumed run then collects it exactly as the uninterrupted one did.
                prefetch = (
                    cfg.overlap
                    and update + 1 < last_update
                    and (update + 1) % cfg.checkpoint_every != 0
                )
                collected = None
                learn_roll = functools.partial(
                    learn,
                    agent,
                    roll,
                    next_value,
                    cfg,
                    device,
                    envs.n_cavs,
                    _update_generator(cfg, update, device),
                    lagged,
                )
                try:
                    if prefetch:
                        next_tau = temperature(
                            global_step + steps_per_update, cfg.total_steps, cfg.env.reward
                        )
                        returns, losses, collected = _learn_beside_rollout(
                            learn_roll, agent, envs, cfg, update, next_tau
                        )
                        lagged = True
                    else:
                        returns, losses = learn_roll()
                except NonFiniteError as exc:
                    kept = (
                        f"checkpoint {ckpt_path} still holds update {saved_update}"
                        if saved_update
                        else "no checkpoint was written"
                    )
                    raise TrainingError(
                        f"update {update + 1}: {exc}; training stopped, this update is not "
                        f"saved and {kept}"
                    ) from None
                global_step += steps_per_update
                lr = agent.optimizer.param_groups[0]["lr"]
                stats = UpdateStats(
                    update + 1, global_step, tau, lr, losses, roll, returns, rollout
                )
                record = progress_record(stats, update_s=time.perf_counter() - t0)
                record["rollout_cpu_s"] = rollout.cpu_seconds
                write_record(record, writer, run_dir / "progress.jsonl")
                bar.update(steps_per_update, record["team_reward"], rollout.episodes)
                if (
                    (update + 1) % cfg.checkpoint_every == 0
                    or update + 1 == last_update
                    or stop.signum is not None
                ):
                    save_checkpoint(ckpt_path, agent, cfg, update + 1, global_step)
                    saved_update = update + 1
                    log.info("checkpoint: update %d, env step %d", update + 1, global_step)
                if stop.signum is not None and update + 1 < last_update:
                    log.warning("stopped after update %d; checkpoint saved", update + 1)
                    raise TrainingInterrupted(stop.signum, update + 1, ckpt_path)
    finally:
        bar.close()
        writer.close()
        envs.close()
    log.info(
        "end: after update %d of %d, env step %d, %.1f s",
        last_update,
        n_updates,
        global_step,
        time.perf_counter() - started_s,
    )
    return run_dir


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
    losses = ppo_update(agent, batch, cfg, n_cavs, generator)
    seconds = {"learner_s": time.perf_counter() - t0, "learner_cpu_s": time.thread_time() - cpu0}
    return returns, {**losses, **seconds}


def _update_generator(cfg: TrainConfig, update: int, device: torch.device):
    """Minibatch RNG of an update: torch's global one, or with ``overlap`` its own.

    Seeded from (run seed, update), so that overlapped runs are reproducible
    and resume exactly without storing its state.
    """
    if not cfg.overlap:
        return None
    return torch.Generator(device=device).manual_seed(cfg.seed * 1_000_003 + update)


def _learn_beside_rollout(
    learn_roll: Callable[[], tuple[np.ndarray, dict[str, float]]],
    agent: Agent,
    envs,
    cfg: TrainConfig,
    update: int,
    next_tau: float,
):
    """Run ``learn_roll`` (:func:`learn` of this update) on a second thread while
    this one collects update + 1's rollout.

    The rollout networks keep the parameters from before this update (no
    sync until both are done), which is the one-update policy lag. torch
    releases the GIL inside its kernels, so the two threads run on two cores
    for most of the update. Returns (returns, losses, next rollout); an error
    of the update is raised here after both finished.
    """
    result: dict = {}

    def run_update() -> None:
        try:
            result["learnt"] = learn_roll()
        except BaseException as exc:  # re-raised on the main thread
            result["error"] = exc

    learner = threading.Thread(target=run_update, name="diacc-learner")
    learner.start()
    try:
        collected = collect_rollout(
            agent, envs, cfg, update + 1, next_tau, sync=False, values=False
        )
    finally:
        learner.join()
    if "error" in result:
        raise result["error"]
    agent.sync_rollout()
    return (*result["learnt"], collected)


# ----------------------------------------------------------------------------- logging
@dataclass
class UpdateStats:
    """What one finished update logs (:func:`progress_record`)."""

    update: int  # 1-based
    global_step: int  # environment steps after the update
    tau: float  # softmin temperature of the rollout
    lr: float
    losses: dict[str, float]  # ppo_update's means
    roll: Rollout
    returns: np.ndarray  # (S, E)
    rollout: RolloutStats


#: Fields of a ``progress.jsonl`` record that measure time: they differ between two
#: runs of the same seed, so identity checks (resume, Ray vs local) leave them out.
TIMING_KEYS = frozenset(
    {"env_steps_per_s", "updates_per_s", "learner_s", "learner_cpu_s", "rollout_cpu_s"}
)


def progress_record(stats: UpdateStats, update_s: float) -> dict:
    """One ``progress.jsonl`` row: losses, rewards, PSAR rates and episode means.

    ``team_reward`` is R, what PPO maximises (paper eq. reward_all), per step
    and environment; ``global_reward`` is its part r_g; ``reward/*`` are the
    other parts (``ego_softmin``, ``individual``, ``completion``, ``warning``:
    the mean warning term of the CAVs on the road, ``delay``: the delay term
    before its weight, ``tau``; ``ego_softmin`` and ``tau`` come from the
    learner's aggregation, :func:`collect_rollout`, the others from the envs);
    ``individual`` is the mean ego reward r_e over the CAVs on the road, what
    the training curves' individual-reward panel plots (``ego_softmin``, its
    softmin-weighted sum, falls as tau anneals whatever the policy does);
    ``psar/*`` the share of CAV decisions on which each rule took effect;
    ``episode/*`` means over the episodes that ended in the rollout
    (``episode/return``: the sum of an episode's team rewards R).
    """
    roll, rollout = stats.roll, stats.rollout
    record = {
        **stats.losses,
        "update": stats.update,
        "global_step": stats.global_step,
        "tau": stats.tau,
        "lr": stats.lr,
        "explained_variance": explained_variance(roll.values.ravel(), stats.returns.ravel()),
        "env_steps_per_s": roll.rewards.size / rollout.seconds,
        "updates_per_s": 1.0 / update_s,
        "worker_restarts": rollout.restarts,
        "team_reward": float(roll.rewards.mean()),
    }
    terms = {key: float(np.mean(values)) for key, values in rollout.reward_terms.items()}
    record["global_reward"] = terms.pop("global")
    record.update({f"reward/{key}": value for key, value in terms.items()})
    for name, count in zip(RULE_NAMES[1:], rollout.psar_counts, strict=True):
        record[f"psar/{name}"] = float(count / max(rollout.decisions, 1))
    if rollout.episodes:
        for key, value in rollout.episodes[0].items():
            if isinstance(value, (int, float)):
                finite = [ep[key] for ep in rollout.episodes if np.isfinite(ep[key])]
                record[f"episode/{key}"] = float(np.mean(finite)) if finite else float("nan")
    return record


def write_record(record: dict, writer: SummaryWriter, progress_path: Path) -> None:
    """Append a record to ``progress.jsonl`` and to TensorBoard (``train/`` unless grouped)."""
    for key, value in record.items():
        if key not in ("update", "global_step"):
            writer.add_scalar(key if "/" in key else f"train/{key}", value, record["global_step"])
    with open_append(progress_path) as fh:
        fh.write(json.dumps(record) + "\n")


def _wait_past_event_files(tb_dir: Path) -> None:
    """Sleep (at most ~1 s) until the clock's second is past every event file's."""
    stamps = [int(p.name.split(".")[3]) for p in tb_dir.glob("events.out.tfevents.*")]
    while stamps and int(time.time()) <= max(stamps):
        time.sleep(0.05)
