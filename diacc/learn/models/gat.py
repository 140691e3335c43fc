"""Dense, batched, masked multi-head graph attention (GAT, Velickovic et al. 2018).

Paper eqs. (TAIE, ITDR): ``e_ij = LeakyReLU(a^T [W h_i || W h_j])``, softmax
over the *existing* neighbours of i only, ``h'_i = sigma(mean_b sum_j
alpha^b_ij W^b h_j)`` (or the heads concatenated).

Graphs are stored as neighbour lists, which covers both uses without loops:

* actor (star graph ego -> neighbours): :meth:`GraphAttention.forward` with
  queries ``(B, Q, F)`` and their own key nodes ``(B, Q, K, F)``;
* critic (global graph): :meth:`GraphAttention.forward_graph` with all nodes
  ``(B, N, F)`` and neighbour indices ``(B, N, K)``.

Two identities keep memory at O(nodes) instead of O(edges x heads x D):
``a^T [W h_i || W h_j] = a_q . W h_i + a_k . W h_j`` (scores are per-node
scalars), and ``sum_j alpha_j W h_j = W sum_j alpha_j h_j`` (the star form
aggregates raw features and projects once per query; the graph form projects
once per node and aggregates with a dense (N x N) attention matrix, or, for
graphs of more than :data:`DENSE_MAX_NODES` nodes (a demand critic), gathers
each node's K' key nodes and pools them as the star form does, O(N K') instead
of O(N^2)).

With ``self_loop`` the query node also attends to itself (standard GAT; the
paper's node set is ``i ∪ M_i``), so an agent with no neighbours still sees
its own state. Masked inputs are zeroed first: padding values (even inf/NaN)
cannot reach outputs or gradients, and a row with no valid key returns zeros.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from diacc.learn.models.errors import ModelError
from diacc.learn.models.layers import masked_softmax

#: Critic graphs up to this many nodes aggregate with a dense (N x N) attention matrix
#: (the paper's cells: fast, and what every trained critic used); larger ones gather.
DENSE_MAX_NODES = 64


class GraphAttention(nn.Module):
    """One multi-head GAT layer on neighbour lists.

    Args:
        in_dim: node feature size F.
        out_dim: per-head output size D.
        heads: number of attention heads.
        concat: concatenate heads (output ``heads * out_dim``) instead of averaging (``out_dim``).
        self_loop: let each query attend to itself as well as to its neighbours.
        negative_slope: LeakyReLU slope of the attention logits.
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        heads: int,
        concat: bool = False,
        self_loop: bool = True,
        negative_slope: float = 0.2,
    ) -> None:
        super().__init__()
        if heads < 1 or out_dim < 1:
            raise ModelError(
                f"GraphAttention needs heads >= 1 and out_dim >= 1, got {heads}, {out_dim}"
            )
        self.heads, self.head_dim, self.concat, self.self_loop = heads, out_dim, concat, self_loop
        self.negative_slope = negative_slope
        self.proj = nn.Linear(in_dim, heads * out_dim, bias=False)  # W (all heads)
        self.att_query = nn.Parameter(torch.empty(heads, out_dim))  # a (query half)
        self.att_key = nn.Parameter(torch.empty(heads, out_dim))  # a (neighbour half)
        nn.init.xavier_uniform_(self.att_query)
        nn.init.xavier_uniform_(self.att_key)

    @property
    def out_features(self) -> int:
        return self.heads * self.head_dim if self.concat else self.head_dim

    def _weights(self) -> Tensor:
        return self.proj.weight.view(self.heads, self.head_dim, -1)  # (H, D, F)

    def _finish(self, out: Tensor) -> Tensor:
        """(..., H, D) head outputs -> sigma(concat or mean); elu(0) = 0 keeps empty rows zero."""
        out = out.flatten(-2) if self.concat else out.mean(-2)
        return nn.functional.elu(out)

    def _project_pooled(self, pooled: Tensor) -> Tensor:
        """W^h applied per head to pooled raw features (..., H, F) -> sigma(...) (..., out).

        Averaged heads need no per-head products: ``mean_h W^h p_h`` is one
        matrix product of the heads' pooled features side by side, (..., H*F),
        with the heads' weights stacked, (H*F, D), divided by H.
        """
        if self.concat:
            return self._finish(torch.einsum("...hf,hdf->...hd", pooled, self._weights()))
        stacked = self._weights().transpose(1, 2).reshape(-1, self.head_dim)  # (H*F, D)
        return nn.functional.elu(pooled.flatten(-2) @ stacked / self.heads)  # (..., D)

    def _alpha(self, score_q: Tensor, score_k: Tensor, valid: Tensor) -> Tensor:
        """score_q (..., H), score_k (..., K', H), valid (..., K') -> weights (..., K', H)."""
        logits = nn.functional.leaky_relu(score_q[..., None, :] + score_k, self.negative_slope)
        return masked_softmax(logits, valid[..., None], dim=-2)

    def forward(
        self,
        h_query: Tensor,
        h_keys: Tensor,
        edge_mask: Tensor,
        query_mask: Tensor | None = None,
        return_attention: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attend from each query to its own key nodes (star graphs).

        Args:
            h_query: (B, Q, F) query nodes (the ego for the actor).
            h_keys: (B, Q, K, F) neighbour nodes of each query.
            edge_mask: (B, Q, K) bool, True where the neighbour exists.
            query_mask: (B, Q) bool or None (all queries exist).
            return_attention: also return the weights (B, Q, K', H), K' = K (+1 with self
                loop, the self weight first).

        Returns:
            (B, Q, out_features); zeros for queries without any valid key.
        """
        if query_mask is None:
            query_mask = torch.ones(h_query.shape[:-1], dtype=torch.bool, device=h_query.device)
        h_query = h_query.masked_fill(~query_mask[..., None], 0.0)  # (B, Q, F)
        keys = h_keys.masked_fill(~edge_mask[..., None], 0.0)  # (B, Q, K, F)
        valid = edge_mask & query_mask[..., None]  # (B, Q, K)
        if self.self_loop:
            keys = torch.cat([h_query[..., None, :], keys], dim=-2)  # (B, Q, 1+K, F)
            valid = torch.cat([query_mask[..., None], valid], dim=-1)  # (B, Q, 1+K)
        weight = self._weights()  # (H, D, F)
        u_query = torch.einsum("hdf,hd->fh", weight, self.att_query)  # (F, H) = W^T a_q
        u_key = torch.einsum("hdf,hd->fh", weight, self.att_key)  # (F, H)
        alpha = self._alpha(h_query @ u_query, keys @ u_key, valid)  # (B, Q, K', H)
        pooled = alpha.transpose(-1, -2) @ keys  # (B, Q, H, F)
        out = self._project_pooled(pooled)  # (B, Q, out_features)
        return (out, alpha) if return_attention else out

    def forward_graph(
        self,
        h_nodes: Tensor,
        neighbours: Tensor,
        edge_mask: Tensor,
        node_mask: Tensor,
        return_attention: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attend over a neighbour-list graph where every node is a query.

        Args:
            h_nodes: (B, N, F) node features.
            neighbours: (B, N, K) int64 indices into the node axis (masked: anything).
            edge_mask: (B, N, K) bool; an edge also needs both end nodes in ``node_mask``.
            node_mask: (B, N) bool, True for real vehicles.
            return_attention: also return the weights (B, N, K', H).

        Returns:
            (B, N, out_features); zeros for masked nodes.
        """
        n_batch, n_nodes, n_nb = neighbours.shape
        h_nodes = h_nodes.masked_fill(~node_mask[..., None], 0.0)  # (B, N, F)
        wh = self.proj(h_nodes).unflatten(-1, (self.heads, self.head_dim))  # (B, N, H, D)
        index = torch.where(edge_mask, neighbours, torch.zeros_like(neighbours))  # (B, N, K)
        flat_index = index.reshape(n_batch, n_nodes * n_nb)  # (B, N*K)
        target_alive = torch.gather(node_mask, 1, flat_index).view(n_batch, n_nodes, n_nb)
        valid = edge_mask & target_alive & node_mask[..., None]  # (B, N, K)
        # a . (W h) = (W^T a) . h: scores from the F-dim input, not the H*D projection.
        weight = self._weights()  # (H, D, F)
        score_q = h_nodes @ torch.einsum("hdf,hd->fh", weight, self.att_query)  # (B, N, H)
        score_node = h_nodes @ torch.einsum("hdf,hd->fh", weight, self.att_key)  # as a key
        score_k = torch.gather(
            score_node, 1, flat_index[..., None].expand(-1, -1, self.heads)
        ).view(n_batch, n_nodes, n_nb, self.heads)  # (B, N, K, H)
        if self.self_loop:
            own = torch.arange(n_nodes, device=index.device).expand(n_batch, n_nodes)[..., None]
            index = torch.cat([own, index], dim=-1)  # (B, N, 1+K)
            score_k = torch.cat([score_node[:, :, None], score_k], dim=2)  # (B, N, 1+K, H)
            valid = torch.cat([node_mask[..., None], valid], dim=-1)  # (B, N, 1+K)
        alpha = self._alpha(score_q, score_k, valid)  # (B, N, K', H)
        if n_nodes > DENSE_MAX_NODES:
            out = self._pool_gathered(h_nodes, index, alpha)
            return (out, alpha) if return_attention else out
        # Dense attention matrix A[b, i, j, h]; masked edges carry zero weight.
        dense = torch.zeros(
            n_batch, n_nodes, n_nodes, self.heads, dtype=alpha.dtype, device=alpha.device
        )
        dense = dense.scatter_add(2, index[..., None].expand(-1, -1, -1, self.heads), alpha)
        out = self._finish(torch.einsum("bijh,bjhd->bihd", dense, wh))  # (B, N, out)
        return (out, alpha) if return_attention else out

    def _pool_gathered(self, h_nodes: Tensor, index: Tensor, alpha: Tensor) -> Tensor:
        """Graph output from each node's own key nodes: sum_j alpha_ij h_j, projected
        (the star form), for graphs too large for the dense (N x N) matrix.

        h_nodes (B, N, F) masked; index (B, N, K') key node of each edge (masked
        edges: any node, with weight 0); alpha (B, N, K', H) -> (B, N, out_features).
        """
        n_batch, n_nodes, n_keys = index.shape
        flat = index.reshape(n_batch, n_nodes * n_keys, 1).expand(-1, -1, h_nodes.shape[-1])
        keys = torch.gather(h_nodes, 1, flat).view(n_batch, n_nodes, n_keys, -1)  # (B,N,K',F)
        return self._project_pooled(alpha.transpose(-1, -2) @ keys)  # (B, N, H, F) pooled


class GlobalGraphAttention(GraphAttention):
    """:class:`GraphAttention` whose ``forward`` is :meth:`~GraphAttention.forward_graph`.

    The critic's layer: called as a module, so that hooks (profiling) see it.
    Same parameters, names and maths as the base class.
    """

    def forward(self, *args, **kwargs):  # type: ignore[override]
        return self.forward_graph(*args, **kwargs)
