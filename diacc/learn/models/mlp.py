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
from diacc.envs.observation import (
    ACTOR_KEYS,
    CRITIC_KEYS,
    N_ACTIONS,
    ObservationSpec,
)
from diacc.learn.models.errors import ModelError
from diacc.learn.models.inputs import TensorDict
from diacc.learn.models.layers import POLICY_GAIN, VALUE_GAIN, mlp, one_hot
from diacc.learn.models.recurrent import Encoder, RecurrentNet


def actor_flat_dim(spec: ObservationSpec) -> int:
    """Length of a flattened ActorObs row."""
    t, k, nodes = spec.history_steps, spec.n_neighbours, spec.node_features
    return (
        spec.self_features
        + t * nodes
        + 2 * (k * t * nodes + k)
        + k * spec.n_actions
        + spec.lane_slots * (spec.lane_features + 1)
        + spec.road_features
        + 2 * spec.n_actions
    )


def critic_flat_dim(spec: ObservationSpec) -> int:
    """Length of a flattened CriticState row."""
    n, k = spec.max_vehicles, spec.n_neighbours
    return (
        n * (spec.critic_node_features + 1)
        + 2 * n * k
        + spec.max_lanes * (spec.lane_features + 1)
        + spec.road_features
        + spec.traffic_features
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
        super().__init__(
            encoder, cfg.gru_hidden, N_ACTIONS, POLICY_GAIN, input_norm=cfg.gru_input_norm
        )


class MLPCritic(RecurrentNet):
    """MAPPO critic: flattened CriticState -> MLP -> GRU -> value."""

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        encoder = _FlatEncoder(critic_flat_dim(spec), cfg, flatten_critic_state, CRITIC_KEYS)
        super().__init__(
            encoder, cfg.gru_hidden, 1, VALUE_GAIN, squeeze=True, input_norm=cfg.gru_input_norm
        )
