"""diacc: dual-interaction-aware cooperative control of CAVs in highway bottlenecks.

PettingZoo entry points, in that library's convention (``from diacc import
parallel_env``)::

    import diacc

    env = diacc.parallel_env(map="train-50", scenario={"n_vehicles": 12})
    observations, infos = env.reset(seed=0)

The factories import the simulator stack only when called, so ``import diacc``
(and the ``diacc`` command's start-up) stays cheap.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from diacc.shipped import data_dir

__version__ = "0.1.0"
__all__ = ["CHECKPOINTS_DIR", "__version__", "env", "load_policy", "parallel_env"]

#: The shipped trained agents, package data in every installation (:mod:`diacc.shipped`;
#: in a clone a link to ``checkpoints/``): ``diacc.load_policy(diacc.CHECKPOINTS_DIR / name)``,
#: or ``diacc.load_policy(name)``, works from any working directory.
CHECKPOINTS_DIR = data_dir("checkpoints")

if TYPE_CHECKING:  # pragma: no cover
    from diacc.envs.env import BottleneckEnv
    from diacc.experiments.agent import TrainedPolicy


def parallel_env(
    render_mode: str | None = None,
    observation_format: str = "dict",
    **config: Any,
) -> BottleneckEnv:
    """The bottleneck environment as a PettingZoo ``ParallelEnv``.

    ``render_mode``: ``None``, ``"rgb_array"`` or ``"human"``;
    ``observation_format``: ``"dict"`` (graph structure as named arrays) or
    ``"flat"`` (one float32 vector, for SB3/SuperSuit; :func:`diacc.envs.spaces.unflatten`
    restores the dict). Every agent's reward is the team reward at the softmin
    temperature ``env.tau`` (``tau_init``); to train on the reward ``diacc train``
    trains on, anneal it over your budget: ``AnnealTemperature(env, total_steps)``
    (:class:`diacc.envs.env.AnnealTemperature`). ``config`` holds fields of
    :class:`diacc.config.EnvConfig` (``backend``, ``map``, ``use_psar``, ...); nested
    sections take a dict or their dataclass, e.g.
    ``scenario={"n_vehicles": 12, "cav_penetration": 0.25}``. Unknown keys raise
    :class:`diacc.config.ConfigError`.
    """
    from diacc.config import ConfigError, override
    from diacc.envs.env import BottleneckEnv, EnvConfig

    if "total_steps" in config:  # the argument of the schedule this env once ran itself
        raise ConfigError(
            "parallel_env takes no total_steps: anneal the temperature with "
            "AnnealTemperature(diacc.parallel_env(...), total_steps) (diacc.envs.env)"
        )
    return BottleneckEnv(
        override(EnvConfig(), config),
        render_mode=render_mode,
        observation_format=observation_format,
    )


def load_policy(path: str | Path, sampled: bool = False) -> TrainedPolicy:
    """A trained agent that acts on PettingZoo observations, keeping each agent's
    recurrent state (:class:`diacc.experiments.agent.TrainedPolicy`); greedy, or ``sampled``.

    ``path``: a checkpoint file, or the name of a shipped one (a file of
    :data:`CHECKPOINTS_DIR`, ``.pt`` optional) when no such file is in the working directory.
    """
    from diacc.experiments.agent import TrainedPolicy
    from diacc.shipped import shipped_checkpoint

    shipped = None if Path(path).exists() else shipped_checkpoint(str(path))
    return TrainedPolicy(shipped or path, sampled=sampled)


def env(render_mode: str | None = None, observation_format: str = "dict", **config: Any):
    """The bottleneck environment as a PettingZoo ``AECEnv`` (PettingZoo's ``env()``
    factory): :func:`parallel_env` with the same arguments, turned into an AEC env by
    PettingZoo's own parallel->AEC wrapper."""
    from pettingzoo.utils.conversions import parallel_to_aec

    return parallel_to_aec(
        parallel_env(render_mode=render_mode, observation_format=observation_format, **config)
    )
