"""Vanilla MAPPO networks: MLP + GRU over the flattened observation / state.

The baseline sees exactly what the graph networks see, flattened: padded
zeros and masks are included as given (masks as 0/1 floats), action indices as
one-hots, and neighbour indices scaled by 1/N (zero where masked). Its input
size therefore depends on K and N, unlike TAIE/ITDR.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diacc.config import ModelConfig
from diacc.models.errors import ModelError
from diacc.models.inputs import TensorDict
from diacc.models.layers import POLICY_GAIN, VALUE_GAIN, mlp, one_hot
from diacc.models.recurrent import Encoder, RecurrentNet
from diacc.models.taie import N_ACTOR_LANES
from diacc.observation import (
    ACTOR_KEYS,
    CRITIC_KEYS,
    CRITIC_NODE_FEATURES,
    LANE_FEATURES,
    MAX_LANES,
    MAX_SEGMENTS,
    N_ACTIONS,
    NODE_FEATURES,
    ROAD_FEATURES_PER_SEGMENT,
    SELF_FEATURES,
    TRAFFIC_FEATURES,
    ObservationSpec,
)

ROAD_DIM = ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS


def actor_flat_dim(spec: ObservationSpec) -> int:
    """Length of a flattened ActorObs row."""
    t, k = spec.history_steps, spec.n_neighbours
    return (
        SELF_FEATURES
        + t * NODE_FEATURES
        + 2 * (k * t * NODE_FEATURES + k)
        + k * N_ACTIONS
        + N_ACTOR_LANES * (LANE_FEATURES + 1)
        + ROAD_DIM
        + 2 * N_ACTIONS
    )


def critic_flat_dim(spec: ObservationSpec) -> int:
    """Length of a flattened CriticState row."""
    n, k = spec.max_vehicles, spec.n_neighbours
    return (
        n * (CRITIC_NODE_FEATURES + 1)
        + 2 * n * k
        + MAX_LANES * (LANE_FEATURES + 1)
        + ROAD_DIM
        + TRAFFIC_FEATURES
    )


def flatten_actor_obs(obs: TensorDict) -> Tensor:
    """ActorObs rows (M, ...) -> (M, actor_flat_dim)."""
    m = obs["self_state"].shape[0]
    parts = [
        obs["self_state"],
        obs["ego_hist"],
        obs["hdv_nodes"],
        obs["hdv_mask"].float(),
        obs["cav_nodes"],
        obs["cav_mask"].float(),
        one_hot(obs["cav_prev_action"], N_ACTIONS),
        obs["lane_stats"],
        obs["lane_mask"].float(),
        obs["road"],
        one_hot(obs["action_memory"], N_ACTIONS),
    ]
    return torch.cat([p.reshape(m, -1) for p in parts], -1)


def flatten_critic_state(state: TensorDict) -> Tensor:
    """CriticState rows (M, ...) -> (M, critic_flat_dim)."""
    m, n_nodes = state["nodes"].shape[:2]
    mask = state["neighbour_mask"]
    neighbours = torch.where(mask, state["neighbours"], 0).float() / n_nodes  # (M, N, K)
    parts = [
        state["nodes"],
        state["node_mask"].float(),
        neighbours,
        mask.float(),
        state["lane_stats"],
        state["lane_mask"].float(),
        state["road"],
        state["traffic"],
    ]
    return torch.cat([p.reshape(m, -1) for p in parts], -1)


class _FlatEncoder(Encoder):
    def __init__(self, in_dim: int, cfg: ModelConfig, flatten, keys: tuple[str, ...]) -> None:
        super().__init__()
        self.input_keys, self.in_dim, self._flatten = keys, in_dim, flatten
        self.body = mlp(in_dim, cfg.hidden_dim, cfg.hidden_dim, cfg.leaky_slope)
        self.out_dim = cfg.hidden_dim

    def forward(self, inputs: TensorDict) -> Tensor:
        flat = self._flatten(inputs)  # (M, in_dim)
        if flat.shape[-1] != self.in_dim:
            raise ModelError(
                f"flattened input has {flat.shape[-1]} features, the MLP was built for "
                f"{self.in_dim} (observation sizes differ from the ObservationSpec)"
            )
        return self.body(flat)


class MLPActor(RecurrentNet):
    """MAPPO actor: flattened ActorObs -> MLP -> GRU -> 5 logits."""

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        encoder = _FlatEncoder(actor_flat_dim(spec), cfg, flatten_actor_obs, ACTOR_KEYS)
        super().__init__(encoder, cfg.gru_hidden, N_ACTIONS, POLICY_GAIN)


class MLPCritic(RecurrentNet):
    """MAPPO critic: flattened CriticState -> MLP -> GRU -> value."""

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        encoder = _FlatEncoder(critic_flat_dim(spec), cfg, flatten_critic_state, CRITIC_KEYS)
        super().__init__(encoder, cfg.gru_hidden, 1, VALUE_GAIN, squeeze=True)
