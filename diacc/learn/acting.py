"""How a trained actor acts: the one step shared by training, evaluation and ``load_policy``.

A training rollout (:func:`diacc.learn.ppo.collect_rollout`), a checkpoint in
``diacc eval`` (:class:`diacc.experiments.policies.CheckpointPolicy`) and an
agent of :func:`diacc.load_policy` (:class:`diacc.experiments.agent.TrainedPolicy`)
all act through :func:`decide`, so they cannot drift apart: the actor's GRU
step, then PSAR's action mask (``env.psar_actions = "masked"``,
:func:`~diacc.envs.action_mask.masked_logits`), then the action:

* greedy: the most likely allowed action (argmax of the masked logits);
* sampled, without a generator: ``Categorical.sample`` on torch's global RNG,
  which training seeds once per run;
* sampled, with a generator: ``torch.multinomial`` on the softmax of the
  masked logits, drawing from that generator, which evaluation seeds with
  each episode's seed (an episode's actions do not depend on the episodes
  before it).

The two sampled draws come from the same distribution; each keeps the random
stream its results were made with.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import torch
from torch import Tensor

from diacc.envs.action_mask import masked_logits
from diacc.learn.models.inputs import TensorDict


@dataclass
class Decision:
    """One step of the actor for B CAVs (:func:`decide`)."""

    logits: Tensor  # (B, 5) the actor's, actions PSAR masks at the dtype's floor
    hidden: Tensor  # (B, H) each CAV's GRU state after the step
    action: Tensor = field(init=False)  # (B,) int64 the actions to send to the env

    @property
    def greedy(self) -> Tensor:
        """(B,) the most likely allowed actions: what a greedy evaluation would pick."""
        return self.logits.argmax(-1)

    @cached_property
    def policy(self) -> torch.distributions.Categorical:
        """The masked action distribution (B, 5), for log-probs; built when asked for,
        since evaluation never asks."""
        return torch.distributions.Categorical(logits=self.logits)


@torch.no_grad()
def decide(
    actor: torch.nn.Module,
    obs: TensorDict,
    hidden: Tensor,
    start: Tensor,
    sampled: bool = False,
    generator: torch.Generator | None = None,
) -> Decision:
    """The actor's step on observations ``obs`` (B rows), from ``hidden`` (B, H) with the
    CAVs whose memory starts afresh in ``start`` (B,) bool: greedy, or ``sampled``
    (from ``generator`` if given, else torch's global RNG; see the module docstring)."""
    logits, hidden = actor(obs, hidden, start)  # (B, 5), (B, H)
    # The mask is all True (a no-op: same numbers) unless env.psar_actions = "masked".
    decision = Decision(masked_logits(logits, obs["action_mask"]), hidden)
    if not sampled:
        decision.action = decision.greedy
    elif generator is None:
        decision.action = decision.policy.sample()
    else:
        probs = torch.softmax(decision.logits, -1)  # (B, 5)
        decision.action = torch.multinomial(probs, 1, generator=generator)[:, 0]
    return decision
