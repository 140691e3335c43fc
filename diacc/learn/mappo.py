"""Recurrent MAPPO for the bottleneck: the entry of ``diacc train``.

The algorithm, readable top to bottom like CleanRL's ``ppo.py`` (rollout,
values, GAE, the clipped update), is :mod:`diacc.learn.ppo`; the run around it
(checkpoints, resume, progress rows, overlap, signals) is
:mod:`diacc.learn.trainer`; the networks are :mod:`diacc.learn.models`, built
into an :class:`~diacc.learn.agent.Agent` by :func:`~diacc.learn.agent.make_agent`.
This module names the entry points users import::

    from diacc.learn.mappo import train
    run_dir = train(TrainConfig(total_steps=20_000))
"""

from __future__ import annotations

from diacc.learn.agent import make_agent
from diacc.learn.trainer import (
    TrainingError,
    TrainingInterrupted,
    check_config,
    seed_everything,
    train,
)

__all__ = [
    "TrainingError",
    "TrainingInterrupted",
    "check_config",
    "make_agent",
    "seed_everything",
    "train",
]
