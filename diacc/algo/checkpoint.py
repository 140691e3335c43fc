"""Checkpoint files: what the trainer saves and what the trainer and the evaluator read.

One ``checkpoint.pt`` holds the run's config, the networks, the optimiser,
the value normaliser and the RNG states (so ``--resume`` continues exactly).
The evaluator needs only the actor and the config (:func:`load_actor`), so
it reads checkpoints through this module and never imports the trainer.
"""

from __future__ import annotations

import random
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from diacc.config import TrainConfig, override
from diacc.errors import DiaccError
from diacc.models.registry import build_policy
from diacc.observation import ObservationSpec

if TYPE_CHECKING:  # pragma: no cover
    from diacc.algo.mappo import Agent


class CheckpointError(DiaccError, RuntimeError):
    """A checkpoint is missing, corrupt, or belongs to another run layout."""


def save_checkpoint(
    path: Path, agent: Agent, cfg: TrainConfig, update: int, global_step: int
) -> None:
    """Write everything ``--resume`` needs, atomically (a killed run keeps the last file)."""
    payload = {
        "format": 1,
        "config": asdict(cfg),
        "variant": cfg.variant,
        "obs_spec": asdict(ObservationSpec.from_config(cfg.env.obs)),
        "update": update,
        "global_step": global_step,
        "actor": agent.actor.state_dict(),
        "critic": agent.critic.state_dict(),
        "value_norm": agent.value_norm.state_dict(),
        "optimizer": agent.optimizer.state_dict(),
        "rng": {
            "python": random.getstate(),
            "numpy": np.random.get_state(),
            "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        },
    }
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def load_checkpoint(path: Path, device: torch.device | str = "cpu") -> dict:
    """Read a checkpoint; raise :class:`CheckpointError` (one line) if it is unusable."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means corrupt
        raise CheckpointError(f"checkpoint {path} is corrupt ({type(exc).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != 1:
        raise CheckpointError(f"checkpoint {path} is not a diacc checkpoint")
    for part in ("actor", "critic"):
        for name, tensor in payload[part].items():
            if torch.is_floating_point(tensor) and not torch.isfinite(tensor).all():
                raise CheckpointError(f"checkpoint {path} has NaN/inf in {part}.{name}")
    return payload


def restore(agent: Agent, payload: dict, cfg: TrainConfig, path: Path) -> None:
    """Load a checkpoint's state into ``agent`` after checking it fits ``cfg``."""
    _check_fits(payload, cfg, path)
    try:
        agent.actor.load_state_dict(payload["actor"])
        agent.critic.load_state_dict(payload["critic"])
    except RuntimeError:
        raise CheckpointError(
            f"checkpoint {path} does not match the {cfg.variant} networks"
        ) from None
    agent.value_norm.load_state_dict(payload["value_norm"])
    agent.optimizer.load_state_dict(payload["optimizer"])


def load_actor(path: Path, variant: str | None = None) -> tuple[torch.nn.Module, TrainConfig, dict]:
    """(actor in eval mode on the CPU, training config, payload) of a checkpoint.

    ``variant``, if given, must be the checkpoint's (guards against comparing
    the wrong runs).
    """
    payload = load_checkpoint(path)
    if variant is not None and payload.get("variant") != variant:
        raise CheckpointError(
            f"checkpoint {path} is for variant {payload.get('variant')!r}, not {variant!r}"
        )
    try:
        cfg = config_from_checkpoint(payload)
    except ValueError as exc:
        raise CheckpointError(f"checkpoint {path} has an unusable config ({exc})") from None
    _check_fits(payload, cfg, path)
    actor, _ = build_policy(cfg.variant, cfg.model, ObservationSpec.from_config(cfg.env.obs))
    try:
        actor.load_state_dict(payload["actor"])
    except RuntimeError:
        raise CheckpointError(f"checkpoint {path} does not match the {cfg.variant} actor") from None
    return actor.eval(), cfg, payload


def _check_fits(payload: dict, cfg: TrainConfig, path: Path) -> None:
    """One-line :class:`CheckpointError` unless the checkpoint's networks fit ``cfg``."""
    if payload["variant"] != cfg.variant:
        raise CheckpointError(
            f"checkpoint {path} is for variant {payload['variant']!r}, not {cfg.variant!r}"
        )
    # Older checkpoints stored only K, T and N; compare what a checkpoint holds.
    spec = asdict(ObservationSpec.from_config(cfg.env.obs))
    if payload["obs_spec"] != {key: spec.get(key) for key in payload["obs_spec"]}:
        raise CheckpointError(f"checkpoint {path} was trained with another observation layout")


def set_rng_state(rng: dict) -> None:
    """Restore the RNG states saved by :func:`save_checkpoint`."""
    random.setstate(rng["python"])
    np.random.set_state(rng["numpy"])
    torch.set_rng_state(rng["torch"].cpu())
    if rng["cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(rng["cuda"])


#: Sections a TrainConfig held at its top level before it nested an EnvConfig.
_ENV_SECTIONS_BEFORE_NESTING = ("backend", "map", "sim", "scenario", "obs", "psar", "reward")


def config_from_checkpoint(payload: dict) -> TrainConfig:
    """Rebuild the TrainConfig stored in a checkpoint (fields it predates take their defaults).

    Checkpoints written before ``TrainConfig.env`` existed kept the
    environment's sections at the top level; they are moved under ``env``.
    """
    saved = dict(payload["config"])
    if "env" not in saved:
        saved["env"] = {k: saved.pop(k) for k in _ENV_SECTIONS_BEFORE_NESTING if k in saved}
    return override(TrainConfig(), flatten_config(saved))


def flatten_config(tree: dict, prefix: str = "") -> dict:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists as tuples), the keys :func:`override` takes."""
    flat = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else value
    return flat
