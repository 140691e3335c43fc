"""The learner's state: networks, optimiser and value normaliser (:class:`Agent`).

Its own module because both the trainer (:mod:`diacc.learn.mappo`, which builds
and updates it) and the checkpoint files (:mod:`diacc.learn.checkpoint`, which
save and restore it) need it, and the trainer imports the checkpoint module:
with the class here neither imports the other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from diacc.learn.valuenorm import ValueNorm


@dataclass
class Agent:
    """Everything that learns or is saved: networks, optimiser, value normaliser.

    ``actor``, ``critic`` and ``value_norm`` are the learner, on the update's
    device. Rollouts use ``rollout_*`` on :data:`diacc.learn.mappo.ROLLOUT_DEVICE`: the same
    modules when the learner is on the CPU, else CPU copies that
    :meth:`sync_rollout` refreshes. The update replays sequences through
    :meth:`replay_actor` / :meth:`replay_critic`: the learner's
    ``forward_sequence``, or its compiled form (``*_sequence``) with
    ``update_compile``.
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
