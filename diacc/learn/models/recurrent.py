"""Encoder -> GRU -> linear head, shared by every actor and critic.

MAPPO practice (CleanRL's recurrent PPO): the carried hidden state is reset by
multiplying with ``1 - episode_start`` before each step, one rollout step uses
:meth:`RecurrentNet.forward`, and training replays chunks with
:meth:`RecurrentNet.forward_sequence`. The encoder runs once over all (T * B)
samples of a chunk; only the cheap GRU cell loops over time.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from diacc.learn.models.inputs import TensorDict, merge_leading, require
from diacc.learn.models.layers import orthogonal_init
from diacc.learn.models.shapes import shapes_from_data


class Encoder(nn.Module):
    """Maps a flat batch of observation tensors (M, ...) to features (M, out_dim)."""

    input_keys: tuple[str, ...] = ()
    out_dim: int = 0

    def forward(self, inputs: TensorDict) -> Tensor:  # pragma: no cover - interface
        raise NotImplementedError


class RecurrentNet(nn.Module):
    """Encoder, one GRU layer and an orthogonally initialised output head.

    Args:
        encoder: feature extractor with ``input_keys`` and ``out_dim``.
        gru_hidden: GRU state size H.
        n_outputs: head outputs (5 logits, or 1 value).
        head_gain: orthogonal gain of the head (0.01 policy, 1 value).
        squeeze: drop the last axis of the head output (value networks).
        input_norm: layer-normalise the encoder's features before the GRU
            (``model.gru_input_norm``, MAPPO's feature normalisation). Without it,
            encoder features a few units large, much of them common to every
            situation, can pin GRU units at +-1 (tanh saturation) whatever the
            input; the norm bounds the GRU's input scale. What it was measured to
            change, and not to change, is in docs/guide/reproducing.md ("What a
            collapsed actor computes").
    """

    def __init__(
        self,
        encoder: Encoder,
        gru_hidden: int,
        n_outputs: int,
        head_gain: float,
        squeeze: bool = False,
        input_norm: bool = False,
    ) -> None:
        super().__init__()
        self.encoder = encoder
        # No parameters without the norm: checkpoints trained before it load unchanged.
        self.input_norm: nn.Module = nn.LayerNorm(encoder.out_dim) if input_norm else nn.Identity()
        self.gru = nn.GRUCell(encoder.out_dim, gru_hidden)
        self.head = nn.Linear(gru_hidden, n_outputs)
        self.squeeze = squeeze
        orthogonal_init(self)
        nn.init.orthogonal_(self.head.weight, gain=head_gain)

    @property
    def hidden_size(self) -> int:
        return self.gru.hidden_size

    def initial_hidden(self, batch: int, device: str | torch.device = "cpu") -> Tensor:
        """Zero hidden state (batch, H) for the start of a rollout."""
        return torch.zeros(batch, self.hidden_size, device=device)

    def _out(self, y: Tensor) -> Tensor:
        return y.squeeze(-1) if self.squeeze else y

    def forward(
        self, inputs: TensorDict, hidden: Tensor, episode_start: Tensor
    ) -> tuple[Tensor, Tensor]:
        """One step: inputs (B, ...), hidden (B, H), episode_start (B,) -> (output, new hidden).

        The output is (B, n_outputs), or (B,) for value networks.
        """
        require(inputs, self.encoder.input_keys, tuple(hidden.shape[:1]), type(self).__name__)
        features = self.input_norm(self.encoder(inputs))  # (B, E)
        keep = 1.0 - episode_start.to(hidden.dtype)  # (B,)
        new_hidden = self.gru(features, hidden * keep[:, None])  # (B, H)
        return self._out(self.head(new_hidden)), new_hidden

    def forward_sequence(
        self, inputs: TensorDict, hidden: Tensor, episode_starts: Tensor, all_states: bool = False
    ) -> tuple[Tensor, Tensor]:
        """Replay a chunk: inputs (T, B, ...), hidden (B, H) at the chunk start, starts (T, B).

        Returns the outputs (T, B, n_outputs) or (T, B) and the hidden state after step T
        (B, H), or with ``all_states`` after every step (T, B, H).
        """
        states = self.hidden_states(inputs, hidden, episode_starts)  # (T, B, H)
        return self._out(self.head(states)), (states if all_states else states[-1])

    def hidden_states(self, inputs: TensorDict, hidden: Tensor, episode_starts: Tensor) -> Tensor:
        """The GRU state after every step of a chunk (T, B, H); arguments as forward_sequence."""
        n_steps, n_batch = episode_starts.shape
        require(inputs, self.encoder.input_keys, (n_steps, n_batch), type(self).__name__)
        flat = merge_leading(inputs, 2)
        needed = needed_rows(inputs, episode_starts)  # (T*B,) or None: every row
        if needed is None:
            features = self.input_norm(self.encoder(flat))  # (T*B, E)
        else:  # encode the rows that matter; the others get zero features
            rows = needed.nonzero().squeeze(1)  # (R,)
            selected = {k: v.index_select(0, rows) for k, v in flat.items()}
            encoded = self.input_norm(self.encoder(selected))  # (R, E)
            features = encoded.new_zeros(n_steps * n_batch, encoded.shape[-1])
            features = features.index_copy(0, rows, encoded)  # (T*B, E)
        # The GRU's input half for all T steps in one product; only the hidden half
        # loops over time. Same formulas and order as torch's CPU GRUCell.
        cell = self.gru
        input_gates = nn.functional.linear(features, cell.weight_ih, cell.bias_ih)  # (T*B, 3H)
        keep = (1.0 - episode_starts.to(hidden.dtype))[..., None]  # (T, B, 1)
        states = []
        for gates_x, keep_t in zip(
            input_gates.view(n_steps, n_batch, -1).unbind(0), keep.unbind(0), strict=True
        ):  # time only: the GRU recursion is sequential
            hidden = gru_step(gates_x, hidden * keep_t, cell)  # (B, H)
            states.append(hidden)
        return torch.stack(states)


#: Encode only the rows that matter when at most this share of a chunk's rows does
#: (gathering and scattering the rows costs more than it saves above it).
SPARSE_ROWS_SHARE = 0.9


def needed_rows(inputs: TensorDict, episode_starts: Tensor) -> Tensor | None:
    """Rows (T*B,) of an actor's chunk whose features can reach a loss, or None for all.

    An agent off the road (``alive`` False: a CAV that left, an empty demand slot)
    adds nothing to any loss, and its GRU state reaches a later step only if that
    step is alive without a reset in between (a new CAV in a slot, an episode
    start, resets it): rows outside both are skipped, which is exact. Demand
    chunks hold many empty slots; a release chunk is nearly all alive, and then
    (above :data:`SPARSE_ROWS_SHARE`) every row is encoded. None also for inputs
    without ``alive`` (critics) and with static shapes (``torch.compile``,
    :func:`~diacc.learn.models.shapes.static_shapes`).
    """
    alive = inputs.get("alive")
    # With static shapes the data-dependent row count would break the graph.
    if alive is None or alive.dtype != torch.bool or not shapes_from_data():
        return None
    needed, carried = alive.clone(), ~episode_starts.bool()  # (T, B) each
    for t in range(alive.shape[0] - 2, -1, -1):  # carried backwards until a reset
        needed[t] |= needed[t + 1] & carried[t + 1]
    needed = needed.reshape(-1)
    if needed.sum() > SPARSE_ROWS_SHARE * needed.numel():
        return None
    return needed


def gru_step(input_gates: Tensor, hidden: Tensor, cell: nn.GRUCell) -> Tensor:
    """One GRU step from precomputed input gates ``W_ih x + b_ih`` (B, 3H) -> new hidden (B, H).

    ``r = sigmoid(i_r + h_r)``, ``z = sigmoid(i_z + h_z)``, ``n = tanh(i_n + r * h_n)``,
    ``h' = (h - n) * z + n`` with ``h_* = W_hh h + b_hh``: :class:`torch.nn.GRUCell`'s
    maths, written out so that the input half can be computed for a whole chunk at once.
    """
    hidden_gates = nn.functional.linear(hidden, cell.weight_hh, cell.bias_hh)  # (B, 3H)
    i_r, i_z, i_n = input_gates.chunk(3, -1)
    h_r, h_z, h_n = hidden_gates.chunk(3, -1)
    reset = torch.sigmoid(h_r + i_r)
    update = torch.sigmoid(h_z + i_z)
    new = torch.tanh(i_n + h_n * reset)
    return (hidden - new) * update + new
