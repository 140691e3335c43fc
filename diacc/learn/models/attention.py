"""Multi-head cross-attention with one query and a padded key set (ITDR).

``softmax(Q_h K_h^T / sqrt(d_k)) V_h`` per head, heads concatenated and
projected by ``W_O`` (paper eqs. in C-IEC). Written out rather than using
``nn.MultiheadAttention`` because that returns NaN when every key is padded
(an empty road) and hides per-head weights, which the tests inspect to make
sure the attention is not degenerate (one pooled key would make it constant).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from diacc.learn.models.errors import ModelError
from diacc.learn.models.layers import masked_softmax


class CrossAttention(nn.Module):
    """Single-query multi-head attention over masked keys.

    Args:
        query_dim: size of the query vector (the traffic feature f_tf).
        key_dim: size of each key/value node feature.
        embed_dim: total attention size; ``embed_dim / heads`` is d_k.
        heads: number of heads.
    """

    def __init__(self, query_dim: int, key_dim: int, embed_dim: int, heads: int) -> None:
        super().__init__()
        if heads < 1 or embed_dim % heads:
            raise ModelError(
                f"cross_dim {embed_dim} must be a positive multiple of cross_heads {heads}"
            )
        self.heads, self.head_dim = heads, embed_dim // heads
        self.q = nn.Linear(query_dim, embed_dim)
        self.k = nn.Linear(key_dim, embed_dim)
        self.v = nn.Linear(key_dim, embed_dim)
        self.out = nn.Linear(embed_dim, embed_dim)
        self.out_dim = embed_dim
        self.last_attention: Tensor | None = None  # (B, heads, N) of the latest call, detached

    def forward(
        self, query: Tensor, keys: Tensor, key_mask: Tensor, return_attention: bool = False
    ) -> Tensor | tuple[Tensor, Tensor]:
        """query (B, Q_in), keys (B, N, K_in), key_mask (B, N) -> (B, embed_dim).

        A batch row whose keys are all masked returns zeros (and zero weights).
        """
        q = self.q(query).unflatten(-1, (self.heads, self.head_dim))  # (B, H, d)
        # K and V in one product (weights side by side; same parameters as two Linears).
        kv = nn.functional.linear(
            keys, torch.cat([self.k.weight, self.v.weight]), torch.cat([self.k.bias, self.v.bias])
        ).unflatten(-1, (2, self.heads, self.head_dim))  # (B, N, 2, H, d)
        k, v = kv.unbind(-3)  # (B, N, H, d) each
        # One query per row: products and sums over d and N stay elementwise, where
        # einsum would permute both operands into a batched matrix product of 1-row matrices.
        scores = (k * q[:, None]).sum(-1) / math.sqrt(self.head_dim)  # (B, N, H)
        weights = masked_softmax(scores, key_mask[..., None], dim=1)  # (B, N, H)
        heads = (weights[..., None] * v).sum(1).flatten(-2)  # (B, H*d)
        has_keys = key_mask.any(-1, keepdim=True).to(heads.dtype)  # (B, 1)
        out = self.out(heads) * has_keys  # (B, embed_dim)
        weights = weights.transpose(1, 2)  # (B, H, N)
        self.last_attention = weights.detach()
        return (out, weights) if return_attention else out
