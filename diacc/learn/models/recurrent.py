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
    """

    def __init__(
        self,
        encoder: Encoder,
        gru_hidden: int,
        n_outputs: int,
        head_gain: float,
        squeeze: bool = False,
    ) -> None:
        super().__init__()
        self.encoder = encoder
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
        features = self.encoder(inputs)  # (B, E)
        keep = 1.0 - episode_start.to(hidden.dtype)  # (B,)
        new_hidden = self.gru(features, hidden * keep[:, None])  # (B, H)
        return self._out(self.head(new_hidden)), new_hidden

    def forward_sequence(
        self, inputs: TensorDict, hidden: Tensor, episode_starts: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Replay a chunk: inputs (T, B, ...), hidden (B, H) at the chunk start, starts (T, B).

        Returns the outputs (T, B, n_outputs) or (T, B) and the hidden state after step T.
        """
        n_steps, n_batch = episode_starts.shape
        require(inputs, self.encoder.input_keys, (n_steps, n_batch), type(self).__name__)
        features = self.encoder(merge_leading(inputs, 2)).reshape(n_steps, n_batch, -1)
        keep = 1.0 - episode_starts.to(hidden.dtype)  # (T, B)
        states = []
        for t in range(n_steps):  # time only: the GRU recursion is sequential
            hidden = self.gru(features[t], hidden * keep[t, :, None])  # (B, H)
            states.append(hidden)
        return self._out(self.head(torch.stack(states))), hidden
