"""ITDR (Integrated Traffic Dynamics Representation) and the C-IEC critic (paper Sec. C-IEC).

Per environment (one :class:`~diacc.envs.observation.CriticState`):

1. static road MLP over the road table, dynamic traffic MLP over the masked
   per-lane statistics, lane mask and traffic globals; concatenated they are
   the traffic feature ``f_tf``;
2. node embedding of every vehicle's state, one GAT over the global graph
   (edges = each vehicle to its K neighbours) -> interaction features;
3. multi-head cross-attention with ``f_tf`` as the single query and *all*
   unmasked node features as keys/values (not a pooled summary: with a single
   key the attention weights would be constant);
4. ``[f_tf, attention output]`` -> GRU -> linear value.

Nothing depends on the padded vehicle count N, so extra masked slots never
change the value, and permuting vehicles only permutes node features.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from diacc.config import ModelConfig
from diacc.envs.observation import (
    CRITIC_KEYS,
    CRITIC_NODE_FEATURES,
    LANE_FEATURES,
    MAX_LANES,
    MAX_SEGMENTS,
    ROAD_FEATURES_PER_SEGMENT,
    TRAFFIC_FEATURES,
    ObservationSpec,
)
from diacc.learn.models.attention import CrossAttention
from diacc.learn.models.errors import ModelError
from diacc.learn.models.gat import GlobalGraphAttention
from diacc.learn.models.inputs import TensorDict
from diacc.learn.models.layers import VALUE_GAIN, embed_present, mlp
from diacc.learn.models.recurrent import Encoder, RecurrentNet
from diacc.learn.models.shapes import shapes_from_data


def trim_padded_nodes(state: TensorDict) -> TensorDict:
    """Drop the node slots behind the last vehicle of the batch (N -> N' <= N).

    The critic pads every state to ``max_vehicles`` slots with the vehicles
    first (at N = 25 of 40 slots, 15 are always empty), and padded slots add
    nothing to any output: their GAT output is zero and the cross-attention
    masks them. Their cost is not nothing (the GAT's attention matrix is
    N x N), so they are cut off here; the outputs are the same. Edges into a
    cut slot point at a padded vehicle, which the GAT ignores anyway; they are
    masked so that no index leaves the shorter node axis. Not with static shapes
    (``torch.compile``, :func:`~diacc.learn.models.shapes.static_shapes`), where the
    data-dependent N' would break the graph or wait for the device.
    """
    node_mask = state["node_mask"]  # (M, N)
    if not shapes_from_data() or node_mask.shape[-1] == 0:
        return state
    slots = torch.arange(1, node_mask.shape[-1] + 1, device=node_mask.device)  # (N,)
    n_used = max(int((node_mask * slots).max()), 1)
    if n_used == node_mask.shape[-1]:
        return state
    neighbours = state["neighbours"][:, :n_used]  # (M, N', K)
    return {
        **state,
        "nodes": state["nodes"][:, :n_used],
        "node_mask": node_mask[:, :n_used],
        "neighbours": neighbours,
        "neighbour_mask": state["neighbour_mask"][:, :n_used] & (neighbours < n_used),
    }


class ITDR(Encoder):
    """CriticState rows (M, ...) -> (M, 2 * hidden_dim + cross_dim)."""

    input_keys = CRITIC_KEYS

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        super().__init__()
        hidden, slope = cfg.hidden_dim, cfg.leaky_slope
        self.road_mlp = mlp(ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS, hidden, hidden, slope)
        self.traffic_mlp = mlp(
            MAX_LANES * LANE_FEATURES + MAX_LANES + TRAFFIC_FEATURES, hidden, hidden, slope
        )
        self.node_embed = mlp(CRITIC_NODE_FEATURES, hidden, hidden, slope)
        # The paper writes ITDR's GAT with one head; we keep gat_heads heads but
        # concatenate hidden/heads-wide heads, which costs a quarter of averaging
        # hidden-wide heads over all N vehicles (the critic's largest layer).
        if hidden % cfg.gat_heads:
            raise ModelError(f"hidden_dim {hidden} must be a multiple of gat_heads {cfg.gat_heads}")
        self.gat = GlobalGraphAttention(
            hidden, hidden // cfg.gat_heads, cfg.gat_heads, concat=True, negative_slope=slope
        )
        self.cross = CrossAttention(2 * hidden, hidden, cfg.cross_dim, cfg.cross_heads)
        self.out_dim = 2 * hidden + cfg.cross_dim

    def traffic_feature(self, state: TensorDict) -> Tensor:
        """f_tf (M, 2 * hidden_dim) from the road table and the dynamic traffic layer."""
        lane_mask = state["lane_mask"]  # (M, L)
        lanes = (state["lane_stats"] * lane_mask[..., None]).flatten(-2)  # (M, L*4)
        dynamic = torch.cat([lanes, lane_mask.float(), state["traffic"]], -1)
        return torch.cat([self.road_mlp(state["road"]), self.traffic_mlp(dynamic)], -1)

    def node_features(self, state: TensorDict) -> Tensor:
        """GAT interaction features of every vehicle (M, N, hidden_dim); zero for padding."""
        node_mask = state["node_mask"]  # (M, N)
        embedded = embed_present(self.node_embed, state["nodes"], node_mask)  # (M, N, E)
        return self.gat(embedded, state["neighbours"], state["neighbour_mask"], node_mask)

    def forward(
        self, state: TensorDict, return_attention: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Encode; with ``return_attention`` also the cross-attention weights (M, heads, N)."""
        f_tf = self.traffic_feature(state)  # (M, 2E)
        used = trim_padded_nodes(state)
        attended, weights = self.cross(
            f_tf, self.node_features(used), used["node_mask"], return_attention=True
        )  # (M, cross_dim), (M, heads, N')
        features = torch.cat([f_tf, attended], -1)
        # Weights over all N slots again (zero on the cut ones), for callers and inspection.
        weights = nn.functional.pad(weights, (0, state["node_mask"].shape[-1] - weights.shape[-1]))
        self.cross.last_attention = weights.detach()  # (M, heads, N)
        return (features, weights) if return_attention else features


class CIECCritic(RecurrentNet):
    """C-IEC critic.

    ``critic(state (B, ...), hidden (B, H), episode_start (B,)) -> (value (B,), hidden)``.
    """

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        super().__init__(
            ITDR(cfg, spec),
            cfg.gru_hidden,
            1,
            VALUE_GAIN,
            squeeze=True,
            input_norm=cfg.gru_input_norm,
        )
