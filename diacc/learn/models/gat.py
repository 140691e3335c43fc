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

    def _score_vectors(self) -> tuple[Tensor, Tensor]:
        """``W^T a`` of both halves of a, (F, H) each, contiguous (fast products both ways)."""
        weight = self._weights()  # (H, D, F)
        u_query = torch.einsum("hdf,hd->fh", weight, self.att_query).contiguous()
        u_key = torch.einsum("hdf,hd->fh", weight, self.att_key).contiguous()
        return u_query, u_key

    def forward(
        self,
        h_query: Tensor,
        h_keys: Tensor,
        edge_mask: Tensor,
        query_mask: Tensor | None = None,
        return_attention: bool = False,
        keys_zeroed: bool = False,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """Attend from each query to its own key nodes (star graphs).

        Args:
            h_query: (..., F) query nodes (the ego for the actor); any leading axes (...).
            h_keys: (..., K, F) neighbour nodes of each query.
            edge_mask: (..., K) bool, True where the neighbour exists.
            query_mask: (...) bool or None (all queries exist).
            return_attention: also return the weights (..., K', H), K' = K (+1 with self
                loop, the self weight first).
            keys_zeroed: the caller guarantees that masked keys are exactly zero (TAIE's
                embeddings of absent nodes), so they need no masking here. Otherwise
                masked keys are replaced by zeros, whatever they hold (even inf/NaN).

        Returns:
            (..., out_features); zeros for queries without any valid key.
        """
        lead, (n_keys, n_features) = h_query.shape[:-1], h_keys.shape[-2:]
        query = h_query.reshape(-1, n_features)  # (M, F)
        keys = h_keys.reshape(-1, n_keys, n_features)  # (M, K, F)
        valid = edge_mask.reshape(-1, n_keys)  # (M, K)
        if not keys_zeroed:
            keys = torch.where(valid[..., None], keys, 0.0)
        if query_mask is not None:
            query_valid = query_mask.reshape(-1, 1)  # (M, 1)
            query = torch.where(query_valid, query, 0.0)
            valid = valid & query_valid
        if self.self_loop:
            own = torch.ones_like(valid[:, :1]) if query_mask is None else query_valid
            keys = torch.cat([query[:, None], keys], dim=1)  # (M, 1+K, F)
            valid = torch.cat([own, valid], dim=1)  # (M, 1+K)
        pooled, alpha = StarPool.apply(
            query, keys, valid, *self._score_vectors(), self.negative_slope
        )
        out = self._project_pooled(pooled).reshape(*lead, -1)  # (..., out_features)
        if not return_attention:
            return out
        return out, alpha.transpose(1, 2).reshape(*lead, keys.shape[1], self.heads)

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


class StarPool(torch.autograd.Function):
    """Attention pooling of star graphs with its backward written out.

    ``pooled[m, h] = sum_k alpha[m, h, k] x[m, k]`` where ``alpha[m, h]`` is the
    softmax over the valid keys k of ``LeakyReLU(q_m . u_q[:, h] + x_mk . u_k[:, h])``
    (the paper's GAT logits with ``u = W^T a``, see the module docstring).

    Why by hand: autograd's backward of these few ops runs matrix products whose
    inner dimension is the head count (4) or the key count (7) on strided views
    (transposes, slices of a concatenation), and CPU kernels run those much slower
    than the same products on contiguous operands; here every product gets
    contiguous operands, and the head axis sits before the key axis throughout.
    Same maths as autograd (tests compare the two). ``alpha`` is returned for
    inspection and carries no gradient.

    Args of ``apply``: q (M, F), x (M, K, F) keys (masked ones zero), valid (M, K)
    bool, u_q and u_k (F, H) contiguous, slope (LeakyReLU). Returns pooled (M, H, F)
    and alpha (M, H, K).
    """

    @staticmethod
    def forward(ctx, q, x, valid, u_q, u_k, slope):
        n, k, f = x.shape
        # (H, F) @ (F, M*K): CPU kernels run this orientation faster than (M*K, F) @ (F, H)
        # (docs/benchmarks, "Training throughput III").
        score_x = (u_k.t() @ x.reshape(n * k, f).t()).view(-1, n, k)  # (H, M, K)
        z = (q @ u_q)[:, :, None] + score_x.permute(1, 0, 2)  # (M, H, K)
        logits = nn.functional.leaky_relu(z, slope)
        alpha = masked_softmax(logits, valid[:, None, :], dim=-1)  # (M, H, K)
        ctx.save_for_backward(q, x, u_q, u_k, z > 0, alpha)
        ctx.slope = slope
        ctx.mark_non_differentiable(alpha)
        return alpha @ x, alpha  # (M, H, F), (M, H, K)

    @staticmethod
    def backward(ctx, g_pooled, _g_alpha):
        q, x, u_q, u_k, positive, alpha = ctx.saved_tensors
        dtypes = q.dtype, x.dtype, u_q.dtype, u_k.dtype
        # Under autocast (bf16) the saved tensors mix dtypes: work in alpha's, whose
        # softmax autocast keeps in float32; each gradient returns in its input's dtype.
        q, x, u_q, u_k = (t.to(alpha.dtype) for t in (q, x, u_q, u_k))
        n, k, f = x.shape
        g_pooled = g_pooled.to(alpha.dtype).contiguous()  # (M, H, F)
        g_alpha = g_pooled @ x.transpose(1, 2)  # (M, H, K)
        # softmax backward (masked weights are 0, so their logits get no gradient)
        g_logits = alpha * (g_alpha - (alpha * g_alpha).sum(-1, keepdim=True))  # (M, H, K)
        g_z = torch.where(positive, g_logits, g_logits * ctx.slope)  # LeakyReLU backward
        g_score_q = g_z.sum(-1)  # (M, H)
        g_score_x = g_z.transpose(1, 2).reshape(n * k, -1)  # (M*K, H), contiguous copy
        x_flat = x.reshape(n * k, f)
        # From the key scores, plus (one pass over the (M, K, F) memory) from the pooling:
        g_x = (g_score_x @ u_k.t()).view(n, k, f)  # (M, K, F)
        g_x = torch.baddbmm(g_x, alpha.transpose(1, 2).contiguous(), g_pooled)
        g_q = g_score_q @ u_q.t()  # (M, F)
        g_u_q = (g_score_q.t() @ q).t()  # (F, H), as an (H, F) product: the faster orientation
        g_u_k = (g_score_x.t() @ x_flat).t()  # (F, H)
        grads = (t.to(dtype) for t, dtype in zip((g_q, g_x, g_u_q, g_u_k), dtypes, strict=True))
        g_q, g_x, g_u_q, g_u_k = grads
        return g_q, g_x, None, g_u_q, g_u_k, None


class GlobalGraphAttention(GraphAttention):
    """:class:`GraphAttention` whose ``forward`` is :meth:`~GraphAttention.forward_graph`.

    The critic's layer: called as a module, so that hooks (profiling) see it.
    Same parameters, names and maths as the base class.
    """

    def forward(self, *args, **kwargs):
        return self.forward_graph(*args, **kwargs)
