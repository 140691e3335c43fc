"""Observation sizes the networks are built for.

The graph networks (TAIE, ITDR) do not depend on the number of neighbours K or
on the padded vehicle count N, only on the history length T; the flat MAPPO
networks depend on all three. Keeping them in one small frozen record lets the
registry build every variant from either the config or a sample observation.
"""

from __future__ import annotations

from dataclasses import dataclass

from diacc.config import ObservationConfig
from diacc.models.errors import ModelError
from diacc.observation import ActorObs, CriticState


@dataclass(frozen=True)
class ObsSpec:
    """Sizes of :class:`ActorObs` / :class:`CriticState` (see ``diacc.observation``)."""

    history_steps: int = 5  # T
    n_neighbours: int = 6  # K
    max_vehicles: int = 40  # N

    def __post_init__(self) -> None:
        for name in ("history_steps", "n_neighbours", "max_vehicles"):
            if getattr(self, name) < 1:
                raise ModelError(f"ObsSpec.{name} must be >= 1, got {getattr(self, name)}")

    @classmethod
    def from_config(cls, obs: ObservationConfig) -> ObsSpec:
        """Spec implied by the observation config the builder uses."""
        return cls(obs.history_steps, obs.n_neighbours, obs.max_vehicles)

    @classmethod
    def from_containers(cls, actor: ActorObs, critic: CriticState) -> ObsSpec:
        """Spec read off one actor observation and one critic state (any batch axes)."""
        history_steps, n_neighbours = actor.hdv_nodes.shape[-2], actor.hdv_nodes.shape[-3]
        return cls(history_steps, n_neighbours, critic.nodes.shape[-2])
