"""Variant name -> (actor, critic), the only place that knows the pairing.

PSAR is an environment flag, so ``diacc-nopsar`` and ``diacc`` share networks.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import nn

from diacc.config import VARIANTS, ModelConfig
from diacc.models.errors import ModelError
from diacc.models.itdr import CIECCritic
from diacc.models.mlp import MLPActor, MLPCritic
from diacc.models.recurrent import RecurrentNet
from diacc.models.spec import ObsSpec
from diacc.models.taie import DIADMActor

_Builder = Callable[[ModelConfig, ObsSpec], RecurrentNet]
_PAIRS: dict[str, tuple[_Builder, _Builder]] = {
    "mappo": (MLPActor, MLPCritic),
    "mappo-iadm": (DIADMActor, MLPCritic),
    "diacc-nopsar": (DIADMActor, CIECCritic),
    "diacc": (DIADMActor, CIECCritic),
}
assert set(_PAIRS) == set(VARIANTS), "registry out of sync with diacc.config.VARIANTS"


def build_policy(
    variant: str, cfg: ModelConfig, obs_spec: ObsSpec
) -> tuple[RecurrentNet, RecurrentNet]:
    """Build the (actor, critic) pair of a variant, orthogonally initialised as in MAPPO.

    Seed torch before calling for reproducible weights.
    """
    if variant not in _PAIRS:
        raise ModelError(f"unknown variant {variant!r}; expected one of {', '.join(VARIANTS)}")
    if cfg.hidden_dim < 1 or cfg.gru_hidden < 1 or cfg.gat_heads < 1:
        raise ModelError(f"ModelConfig sizes must be >= 1, got {cfg}")
    actor_cls, critic_cls = _PAIRS[variant]
    return actor_cls(cfg, obs_spec), critic_cls(cfg, obs_spec)


def parameter_count(module: nn.Module) -> int:
    """Trainable scalars of a network."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
