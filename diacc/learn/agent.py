"""The learner's state: networks, optimiser and value normaliser (:class:`Agent`).

Its own module because the algorithm (:mod:`diacc.learn.ppo`, which updates
it), the trainer (:mod:`diacc.learn.trainer`, which builds it with
:func:`make_agent`) and the checkpoint files (:mod:`diacc.learn.checkpoint`,
which save and restore it) all need it: with the class here none of them
imports another for it.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import torch

from diacc.config import TrainConfig
from diacc.envs.observation import ObservationSpec
from diacc.learn.loss import minibatch_loss
from diacc.learn.models.agent_value import AgentValueCritic
from diacc.learn.models.registry import build_networks
from diacc.learn.valuenorm import ValueNorm


@dataclass
class Agent:
    """Everything that learns or is saved: networks, optimiser, value normaliser.

    ``actor``, ``critic`` and ``value_norm`` are the learner, on the update's
    device. Rollouts use ``rollout_*`` on :data:`ROLLOUT_DEVICE`: the same
    modules when the learner is on the CPU, else CPU copies that
    :meth:`sync_rollout` refreshes. The update replays sequences through
    :meth:`replay_actor` / :meth:`replay_critic`: the learner's
    ``forward_sequence``, or its compiled form (``*_sequence``) with
    ``update_compile``; the static update (:mod:`diacc.learn.static_update`)
    compiles its whole minibatch loss instead (``static_loss``).
    """

    actor: torch.nn.Module
    critic: torch.nn.Module
    value_norm: ValueNorm
    optimizer: torch.optim.Optimizer
    rollout_actor: torch.nn.Module | None = None
    rollout_critic: torch.nn.Module | None = None
    rollout_value_norm: ValueNorm | None = None
    actor_sequence: Callable | None = None
    critic_sequence: Callable | None = None
    #: the static update's compiled minibatch loss (``update_compile`` on that path)
    static_loss: Callable | None = None

    def __post_init__(self) -> None:
        self.rollout_actor = self.actor if self.rollout_actor is None else self.rollout_actor
        self.rollout_critic = self.critic if self.rollout_critic is None else self.rollout_critic
        if self.rollout_value_norm is None:
            self.rollout_value_norm = self.value_norm

    def replay_actor(self, *args) -> tuple[torch.Tensor, torch.Tensor]:
        """The learner actor's ``forward_sequence`` (compiled if ``actor_sequence`` is set)."""
        return (self.actor_sequence or self.actor.forward_sequence)(*args)

    def replay_critic(self, *args) -> tuple[torch.Tensor, torch.Tensor]:
        """The learner critic's ``forward_sequence`` (compiled if ``critic_sequence`` is set)."""
        return (self.critic_sequence or self.critic.forward_sequence)(*args)

    def sync_rollout(self) -> None:
        """Copy the learner's weights and value statistics into the rollout copies."""
        pairs = (
            (self.rollout_actor, self.actor),
            (self.rollout_critic, self.critic),
            (self.rollout_value_norm, self.value_norm),
        )
        for copy_, learner in pairs:
            if copy_ is not learner:
                copy_.load_state_dict(learner.state_dict())


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
    if cfg.update_compile and update_path(cfg, device) == "static":
        # CUDA: the forward and backward graphs become CUDA graphs, replayed per step.
        mode = "reduce-overhead" if device.type == "cuda" else None
        extras["static_loss"] = torch.compile(minibatch_loss, mode=mode, dynamic=False)
    elif cfg.update_compile:
        extras["actor_sequence"] = torch.compile(actor.forward_sequence)
        extras["critic_sequence"] = torch.compile(critic.forward_sequence)
    return Agent(actor, critic, value_norm, optimizer, **extras)


def update_path(cfg: TrainConfig, device: torch.device) -> str:
    """The PPO update ``cfg.update_path`` means on ``device``: ``auto`` is ``static``
    (:mod:`diacc.learn.static_update`) on CUDA, where launches and host syncs cost
    more than the maths, and ``eager`` elsewhere, where skipping the rows of CAVs
    off the road (:func:`~diacc.learn.models.recurrent.needed_rows`) saves work."""
    if cfg.update_path != "auto":
        return cfg.update_path
    return "static" if device.type == "cuda" else "eager"
