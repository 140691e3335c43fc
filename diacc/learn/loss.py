"""The PPO loss of one minibatch: the maths both update paths share.

:func:`diacc.learn.ppo.ppo_update` (eager: whole sequences per minibatch,
checks after every step) and :func:`diacc.learn.static_update.static_ppo_update`
(padded minibatches of one size, no host syncs) both take their losses from
:func:`minibatch_loss`, so the two paths differ only in how they draw, pad and
check minibatches, never in the objective.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
import torch.nn.functional as F

from diacc.config import TrainConfig
from diacc.envs.action_mask import masked_logits
from diacc.errors import DiaccError
from diacc.learn.buffer import Batch


class Replays(Protocol):
    """What the loss uses of an :class:`~diacc.learn.agent.Agent`: its sequence replays
    (a protocol: agent.py imports this module, to compile :func:`minibatch_loss`)."""

    def replay_actor(self, *args) -> tuple[torch.Tensor, torch.Tensor]: ...

    def replay_critic(self, *args) -> tuple[torch.Tensor, torch.Tensor]: ...


class NonFiniteError(DiaccError, RuntimeError):
    """A loss, gradient or parameter became NaN/inf; the update must not be kept."""


def first_nonfinite(net: torch.nn.Module, part: str, grad: bool = False) -> str | None:
    """First parameter (or gradient) holding NaN/inf, by name (``critic.head.weight``)."""
    for name, param in net.named_parameters():
        tensor = param.grad if grad else param
        if tensor is not None and not torch.isfinite(tensor).all():
            return f"{part}.{name}"
    return None if not grad else f"{part} (norm)"


def evaluate_batch(
    agent: Replays,
    batch: Batch,
    envs_idx: torch.Tensor,
    n_cavs: int,
    static: bool = False,
):
    """Replay critic sequences ``envs_idx`` and their CAVs' actor sequences.

    ``static``: the distribution is left unvalidated (a host read of the logits);
    run it inside :func:`~diacc.learn.models.shapes.static_shapes` too, so that no
    shape depends on the data and nothing waits for the device.
    Returns (new log-probs (L, b_a), entropy (L, b_a), normalised values (L, b_c),
    actor sequence indices b_a).
    """
    dist, agents_idx = actor_distribution(agent, batch, envs_idx, n_cavs, static)
    values, _ = agent.replay_critic(
        {k: v[:, envs_idx] for k, v in batch.critic_state.items()},
        batch.critic_h0[envs_idx],
        batch.critic_start[:, envs_idx],
    )
    # float(): under bf16 autocast the networks return bf16; losses are taken in fp32.
    return dist.log_prob(batch.actions[:, agents_idx]), dist.entropy(), values.float(), agents_idx


def actor_distribution(
    agent: Replays, batch: Batch, envs_idx: torch.Tensor, n_cavs: int, static: bool = False
):
    """The learner actor's action distribution (L, b_a, 5) on the CAVs of critic
    sequences ``envs_idx``, and their actor sequence indices b_a (``static``: as
    :func:`evaluate_batch`)."""
    agents_idx = (
        envs_idx[:, None] * n_cavs + torch.arange(n_cavs, device=envs_idx.device)
    ).reshape(-1)
    logits, _ = agent.replay_actor(
        {k: v[:, agents_idx] for k, v in batch.actor_obs.items()},
        batch.actor_h0[agents_idx],
        batch.actor_start[:, agents_idx],
    )
    logits = masked_logits(logits.float(), batch.actor_obs["action_mask"][:, agents_idx])
    # validate_args checks the logits on the host (a sync per minibatch on a GPU)
    dist = torch.distributions.Categorical(logits=logits, validate_args=False if static else None)
    return dist, agents_idx


#: The parts of a minibatch's loss, in the order :class:`LossParts` stacks them.
LOSS_NAMES = ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac")


@dataclass
class LossParts:
    """One minibatch's loss and its diagnostics, all 0-d tensors (no host sync)."""

    loss: torch.Tensor  # what backward() runs on
    policy_loss: torch.Tensor
    value_loss: torch.Tensor
    entropy: torch.Tensor
    approx_kl: torch.Tensor  # no grad
    clipfrac: torch.Tensor  # no grad

    def stacked(self) -> torch.Tensor:
        """(5,) the diagnostics in :data:`LOSS_NAMES` order, detached."""
        return torch.stack([getattr(self, name).detach() for name in LOSS_NAMES])


def minibatch_loss(
    agent: Replays,
    batch: Batch,
    returns_n: torch.Tensor,
    envs_idx: torch.Tensor,
    cfg: TrainConfig,
    n_cavs: int,
    valid: torch.Tensor | None = None,
) -> LossParts:
    """Clipped PPO's loss on critic sequences ``envs_idx`` (b_c,) and their CAVs.

    ``returns_n``: the batch's returns, normalised (L, B_c[, C]). ``valid`` (b_c,)
    float: 1 for a real sequence, 0 for padding (the static path's last minibatch);
    padded sequences add nothing, and every mean is over the real ones, so the loss
    equals that of the minibatch without its padding. None: all real (eager path).
    CAVs that have left add nothing to the actor losses (death masking).
    """
    with torch.autocast(returns_n.device.type, torch.bfloat16, enabled=cfg.update_bf16):
        logprob, entropy, value, agents_idx = evaluate_batch(
            agent, batch, envs_idx, n_cavs, static=valid is not None
        )
    mask = batch.alive[:, agents_idx]  # (L, b_a): dead CAVs add nothing
    if valid is not None:
        mask = mask * valid.repeat_interleave(n_cavs)[None, :]  # (L, b_a)
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
    old_v, target = batch.old_values_normalised[:, envs_idx], returns_n[:, envs_idx]
    v_clipped = old_v + (value - old_v).clamp(-cfg.clip, cfg.clip)
    value_terms = torch.max(
        F.huber_loss(value, target, delta=cfg.huber_delta, reduction="none"),
        F.huber_loss(v_clipped, target, delta=cfg.huber_delta, reduction="none"),
    )  # (L, b_c) or (L, b_c, C)
    if valid is None:
        value_loss = value_terms.mean()
    else:  # the mean over the real sequences' terms
        weight = valid.view(1, -1, *([1] * (value_terms.dim() - 2))).expand_as(value_terms)
        value_loss = (value_terms * weight).sum() / weight.sum().clamp(min=1.0)
    loss = policy_loss - cfg.entropy_coef * entropy_mean + cfg.value_coef * value_loss
    with torch.no_grad():
        approx_kl = (((ratio - 1) - log_ratio) * mask).sum() / n_alive
        clipfrac = (((ratio - 1).abs() > cfg.clip).float() * mask).sum() / n_alive
    return LossParts(loss, policy_loss, value_loss, entropy_mean, approx_kl, clipfrac)
