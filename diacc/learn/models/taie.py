"""TAIE (Trajectory-Aware Interaction Encoder) and the D-IADM actor (paper Sec. D-IADM).

Per CAV (one row of :class:`~diacc.envs.observation.ActorObs`):

1. node embedding: each node's history (T x NODE_FEATURES, flattened) -> MLP;
2. CAV-HDV graph: GAT over the star graph ego -> HDV neighbours -> ``f_H``;
3. CAV-CAV graph: same, but every CAV node also carries that CAV's previous
   (refined) action as a one-hot, the ego its own previous refined action ->
   ``f_C``. Separate embeddings and GATs for the two graphs are the point of
   the paper: cooperative and observed interactions are different;
4. context MLP over masked lane statistics, lane mask, road table and
   self state -> ``f_dt``;
5. fusion MLP over ``[f_H, f_C, f_dt]`` -> ``f``.

The actor then appends the action memory (one-hot of the proposed and of the
refined previous action), runs a GRU and outputs 5 categorical logits.
"""

from __future__ import annotations

import torch
from torch import Tensor

from diacc.config import ModelConfig
from diacc.envs.observation import (
    ACTOR_KEYS,
    N_ACTIONS,
    ObservationSpec,
)
from diacc.learn.models.errors import ModelError
from diacc.learn.models.gat import GraphAttention
from diacc.learn.models.inputs import TensorDict
from diacc.learn.models.layers import POLICY_GAIN, embed_present, mlp, one_hot
from diacc.learn.models.recurrent import Encoder, RecurrentNet


class TAIE(Encoder):
    """Trajectory-aware interaction encoder: ActorObs rows (M, ...) -> (M, hidden_dim).

    Independent of the number of neighbour slots K, so padding never changes it.
    """

    input_keys = ACTOR_KEYS

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        super().__init__()
        hidden, slope = cfg.hidden_dim, cfg.leaky_slope
        history_in = spec.history_steps * spec.node_features
        self.hdv_embed = mlp(history_in, hidden, hidden, slope)
        self.cav_embed = mlp(history_in + N_ACTIONS, hidden, hidden, slope)
        # Heads: averaged hidden-wide heads (the paper's eq. TAIE), or with
        # ``taie_concat_heads`` hidden/heads-wide heads concatenated (the usual
        # multi-head layout, as ITDR does): same output width, a quarter of the
        # projection work. An option because it changes what is learnt.
        if cfg.taie_concat_heads and hidden % cfg.gat_heads:
            raise ModelError(f"hidden_dim {hidden} must be a multiple of gat_heads {cfg.gat_heads}")
        head_dim = hidden // cfg.gat_heads if cfg.taie_concat_heads else hidden
        self.hdv_gat, self.cav_gat = (
            GraphAttention(
                hidden, head_dim, cfg.gat_heads, concat=cfg.taie_concat_heads, negative_slope=slope
            )
            for _ in range(2)
        )
        context_in = (
            spec.lane_slots * spec.lane_features
            + spec.lane_slots
            + spec.road_features
            + spec.self_features
        )
        self.context = mlp(context_in, hidden, hidden, slope)
        self.fusion = mlp(3 * hidden, hidden, hidden, slope)
        self.out_dim = hidden

    def forward(
        self, obs: TensorDict, return_attention: bool = False
    ) -> Tensor | tuple[Tensor, dict[str, Tensor]]:
        """Encode a flat batch; with ``return_attention`` also the GAT weights of both graphs."""
        ego_hist = obs["ego_hist"].flatten(-2)  # (M, T*F)
        hdv_mask, cav_mask = obs["hdv_mask"], obs["cav_mask"]  # (M, K)
        # Padded slots are never embedded (embed_present), so they need no zeroing here.
        hdv_hist = obs["hdv_nodes"].flatten(-2)  # (M, K, T*F)
        cav_hist = obs["cav_nodes"].flatten(-2)  # (M, K, T*F)
        cav_action = torch.where(cav_mask, obs["cav_prev_action"], 0)  # (M, K)
        ego_action = obs["action_memory"][..., 1]  # (M,) refined previous action

        # Absent neighbours embed to exact zeros (embed_present): no masking in the GATs.
        f_hdv, att_hdv = self.hdv_gat(
            self.hdv_embed(ego_hist),  # (M, E)
            embed_present(self.hdv_embed, hdv_hist, hdv_mask),  # (M, K, E)
            hdv_mask,
            return_attention=True,
            keys_zeroed=True,
        )
        f_cav, att_cav = self.cav_gat(
            self.cav_embed(torch.cat([ego_hist, one_hot(ego_action, N_ACTIONS)], -1)),
            embed_present(
                self.cav_embed, torch.cat([cav_hist, one_hot(cav_action, N_ACTIONS)], -1), cav_mask
            ),  # (M, K, E)
            cav_mask,
            return_attention=True,
            keys_zeroed=True,
        )
        lane_mask = obs["lane_mask"]  # (M, 3)
        lanes = (obs["lane_stats"] * lane_mask[..., None]).flatten(-2)  # (M, 3*4)
        f_context = self.context(
            torch.cat([lanes, lane_mask.float(), obs["road"], obs["self_state"]], -1)
        )  # (M, E)
        fused = self.fusion(torch.cat([f_hdv, f_cav, f_context], -1))  # (M, E)
        if return_attention:
            return fused, {"hdv": att_hdv, "cav": att_cav}  # (M, 1+K, H) each
        return fused


class DIADMEncoder(Encoder):
    """TAIE features with the action memory appended (the GRU input of D-IADM)."""

    input_keys = ACTOR_KEYS

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        super().__init__()
        self.taie = TAIE(cfg, spec)
        self.out_dim = self.taie.out_dim + 2 * N_ACTIONS

    def forward(self, obs: TensorDict) -> Tensor:
        memory = one_hot(obs["action_memory"], N_ACTIONS).flatten(-2)  # (M, 2*5)
        return torch.cat([self.taie(obs), memory], -1)  # (M, E + 10)


class DIADMActor(RecurrentNet):
    """D-IADM actor.

    ``actor(obs (B, ...), hidden (B, H), episode_start (B,)) -> (logits (B, 5), hidden)``.
    """

    def __init__(self, cfg: ModelConfig, spec: ObservationSpec) -> None:
        super().__init__(
            DIADMEncoder(cfg, spec),
            cfg.gru_hidden,
            N_ACTIONS,
            POLICY_GAIN,
            input_norm=cfg.gru_input_norm,
        )
