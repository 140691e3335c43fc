"""Network names of :data:`diacc.config.VARIANT_TABLE` -> network classes.

PSAR is an environment flag, so ``diacc-nopsar`` and ``diacc`` share networks.
"""

from __future__ import annotations

from collections.abc import Callable

from torch import nn

from diacc.config import VARIANT_TABLE, VARIANTS, ModelConfig
from diacc.envs.observation import ObservationSpec
from diacc.learn.models.errors import ModelError
from diacc.learn.models.itdr import CIECCritic
from diacc.learn.models.mlp import MLPActor, MLPCritic
from diacc.learn.models.recurrent import RecurrentNet
from diacc.learn.models.taie import DIADMActor

_Builder = Callable[[ModelConfig, ObservationSpec], RecurrentNet]
_ACTORS: dict[str, _Builder] = {"mlp": MLPActor, "diadm": DIADMActor}
_CRITICS: dict[str, _Builder] = {"mlp": MLPCritic, "ciec": CIECCritic}


def build_networks(
    variant: str, cfg: ModelConfig, obs_spec: ObservationSpec
) -> tuple[RecurrentNet, RecurrentNet]:
    """Build the (actor, critic) pair of a variant, orthogonally initialised as in MAPPO.

    Seed torch before calling for reproducible weights.
    """
    if variant not in VARIANT_TABLE:
        raise ModelError(f"unknown variant {variant!r}; expected one of {', '.join(VARIANTS)}")
    if cfg.hidden_dim < 1 or cfg.gru_hidden < 1 or cfg.gat_heads < 1:
        raise ModelError(f"ModelConfig sizes must be >= 1, got {cfg}")
    networks = VARIANT_TABLE[variant]
    return _ACTORS[networks.actor](cfg, obs_spec), _CRITICS[networks.critic](cfg, obs_spec)


def parameter_count(module: nn.Module) -> int:
    """Trainable scalars of a network."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
