"""A trained agent for Python users: acts on PettingZoo observations, keeps its memory.

The evaluator drives checkpoints through the batched :class:`ActorObs`
(:class:`diacc.experiments.policies.CheckpointPolicy`); both act through
:func:`diacc.learn.acting.decide`, as training does. Someone holding a
``diacc.parallel_env`` has a dict of per-agent observations instead, and
agents that leave the road mid-episode. :func:`load_policy` gives them::

    policy = diacc.load_policy("checkpoints/diacc-train50-paper-congestion-s1.pt")
    env = policy.make_env()              # the env the agent was trained in
    observations, infos = env.reset(seed=0)
    policy.reset(seed=0)
    while env.agents:
        observations, rewards, terms, truncs, infos = env.step(policy.act(observations))

The actor is recurrent (a GRU per CAV): :class:`TrainedPolicy` keeps one
hidden state per agent name, starts it at zero the first time it sees the
agent, and forgets agents that no longer appear (PettingZoo never revives
them). Observations may be in the ``"dict"`` or the ``"flat"`` format
(:mod:`diacc.envs.spaces`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from diacc.config import EnvConfig, override
from diacc.envs.observation import ObservationSpec
from diacc.envs.spaces import SpaceError, actor_obs_from_rows

__all__ = ["TrainedPolicy"]


class TrainedPolicy:
    """A checkpoint's actor acting on PettingZoo observations (see module docstring).

    Args:
        path: a ``checkpoint.pt`` (or a run directory holding one).
        sampled: draw actions from the policy's distribution (seeded by
            :meth:`reset`) instead of taking the most likely one.
    """

    def __init__(self, path: str | Path, sampled: bool = False) -> None:
        import torch

        from diacc.experiments.policies import PolicyError, build_policy, parse_policy

        if not isinstance(sampled, bool):  # "yes" or "no" would both sample
            raise PolicyError(f"sampled must be True or False, got {sampled!r}")
        spec = parse_policy(str(path), sampled=sampled)
        if spec.is_baseline or spec.is_scripted:
            raise PolicyError(f"{path!s} is a baseline, not a checkpoint; load_policy needs a .pt")
        checkpoint = build_policy(spec)
        self.path = Path(spec.name)
        self.sampled = sampled
        self.actor = checkpoint.actor
        self.env_config: EnvConfig = checkpoint.base
        self.variant: str = checkpoint.train_config.variant
        self.spec = ObservationSpec.from_config(self.env_config.obs)
        self._hidden_size = checkpoint.hidden_size
        self._hidden: dict[str, torch.Tensor] = {}  # agent -> (H,)
        self._generator = torch.Generator()
        self.reset(seed=0)

    def make_env(
        self, render_mode: str | None = None, observation_format: str = "dict", **config: Any
    ):
        """A ``ParallelEnv`` with the config the agent was trained with (PSAR as its
        variant uses it), changed by ``config`` (dotted or nested keys, as
        :func:`diacc.parallel_env`)."""
        from diacc.envs.env import BottleneckEnv

        return BottleneckEnv(
            override(self.env_config, config),
            render_mode=render_mode,
            observation_format=observation_format,
        )

    def reset(self, seed: int = 0) -> None:
        """Forget every agent's memory; call at each ``env.reset``. ``seed`` seeds sampling."""
        self._hidden.clear()
        self._generator.manual_seed(seed)

    def act(self, observations: Mapping[str, Any]) -> dict[str, int]:
        """One action per agent in ``observations`` (PettingZoo's dict of agent -> obs)."""
        import torch

        from diacc.learn.acting import decide
        from diacc.learn.models.inputs import to_tensors

        agents = list(observations)
        self._hidden = {a: h for a, h in self._hidden.items() if a in observations}
        if not agents:
            return {}
        try:
            batch = actor_obs_from_rows(self.spec, [observations[a] for a in agents])  # C rows
        except ValueError as exc:
            raise SpaceError(
                f"observations do not fit checkpoint {self.path}'s layout ({exc}); make the env "
                "with policy.make_env()"
            ) from None
        zero = torch.zeros(self._hidden_size)
        start = torch.tensor([a not in self._hidden for a in agents])  # (C,)
        hidden = torch.stack([self._hidden.get(a, zero) for a in agents])  # (C, H)
        step = decide(self.actor, to_tensors(batch), hidden, start, self.sampled, self._generator)
        self._hidden.update(zip(agents, step.hidden, strict=True))  # (C, H)
        return {a: int(x) for a, x in zip(agents, step.action.tolist(), strict=True)}
