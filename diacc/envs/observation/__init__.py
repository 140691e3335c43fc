"""Shared observations: TrafficState -> actor observations and critic state.

* ``layout``: what each row and column holds, every size
  (:class:`ObservationSpec`), the containers :class:`ActorObs` and
  :class:`CriticState`.
* ``actor_features`` / ``critic_features``: the features, small functions
  each filling some fields (as sumo-rl's ``ObservationFunction``).
* ``scales``: what they read of the map, computed once; ``frames``: the
  history and the neighbour search of one instant.
* ``builder``: :class:`ObservationBuilder` composes the features that
  ``features_for`` picks for the config's options.
"""

from diacc.envs.observation.builder import Features, ObservationBuilder, features_for
from diacc.envs.observation.layout import (
    ACTOR_KEYS,
    COUNT_SCALE,
    CRITIC_KEYS,
    CRITIC_NODE_FEATURES,
    DENSITY_SCALE_VEH_PER_KM,
    DX_SCALE_M,
    FEATURE_CLIP,
    LANE_END_SCALE_M,
    LANE_FEATURES,
    LANE_SLOTS,
    MAX_LANES,
    MAX_SEGMENTS,
    N_ACTIONS,
    NODE_FEATURES,
    ROAD_FEATURES_PER_SEGMENT,
    SELF_FEATURES,
    TRAFFIC_FEATURES,
    ActorObs,
    CriticState,
    ObservationError,
    ObservationSpec,
    check_road,
)

__all__ = [
    "ACTOR_KEYS",
    "COUNT_SCALE",
    "CRITIC_KEYS",
    "CRITIC_NODE_FEATURES",
    "DENSITY_SCALE_VEH_PER_KM",
    "DX_SCALE_M",
    "FEATURE_CLIP",
    "LANE_END_SCALE_M",
    "LANE_FEATURES",
    "LANE_SLOTS",
    "MAX_LANES",
    "MAX_SEGMENTS",
    "N_ACTIONS",
    "NODE_FEATURES",
    "ROAD_FEATURES_PER_SEGMENT",
    "SELF_FEATURES",
    "TRAFFIC_FEATURES",
    "ActorObs",
    "CriticState",
    "Features",
    "ObservationBuilder",
    "ObservationError",
    "ObservationSpec",
    "check_road",
    "features_for",
]
