"""Small building blocks shared by the networks: MLPs, masked softmax, MAPPO init."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from diacc.learn.models.shapes import shapes_from_data

#: Orthogonal-init gains of MAPPO: hidden layers, policy logits, value output.
HIDDEN_GAIN = math.sqrt(2.0)
POLICY_GAIN = 0.01
VALUE_GAIN = 1.0


def mlp(
    in_dim: int, hidden_dim: int, out_dim: int, slope: float, n_layers: int = 2
) -> nn.Sequential:
    """Feature extractor: ``n_layers`` Linear + LeakyReLU blocks (the output is activated too)."""
    dims = [in_dim] + [hidden_dim] * (n_layers - 1) + [out_dim]
    layers: list[nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:], strict=True):
        layers += [nn.Linear(a, b), nn.LeakyReLU(slope)]
    return nn.Sequential(*layers)


def masked_softmax(scores: Tensor, mask: Tensor, dim: int) -> Tensor:
    """Softmax over ``dim`` restricted to ``mask``; rows without any valid entry give zeros.

    Filling with the most negative finite float (not -inf) keeps fully masked
    rows finite, and multiplying by the mask turns their uniform weights into
    zeros, so neither the output nor its gradient can become NaN.
    """
    filled = scores.masked_fill(~mask, torch.finfo(scores.dtype).min)
    return torch.softmax(filled, dim=dim) * mask.to(scores.dtype)


def orthogonal_init(module: nn.Module, gain: float = HIDDEN_GAIN) -> None:
    """MAPPO initialisation: orthogonal weights, zero biases, for Linear and GRU cells."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            nn.init.orthogonal_(m.weight, gain=gain)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, (nn.GRUCell, nn.GRU)):
            for name, p in m.named_parameters():
                if "weight" in name:
                    nn.init.orthogonal_(p)
                else:
                    nn.init.zeros_(p)


def one_hot(index: Tensor, n_classes: int) -> Tensor:
    """Float one-hot of int64 indices (``F.one_hot`` raises on out-of-range values)."""
    return nn.functional.one_hot(index, n_classes).to(torch.float32)


def embed_present(embed: torch.nn.Module, nodes: Tensor, mask: Tensor) -> Tensor:
    """Embed only the nodes that exist: nodes (M, K, F), mask (M, K) -> (M, K, E), zeros elsewhere.

    Padding is common (each CAV's K neighbours are split over an HDV and a CAV
    set of K slots each; the critic pads to ``max_vehicles``), so skipping it
    saves a large share of the embedding cost. Padded rows are exactly zero.
    Under ``torch.compile`` or :func:`~diacc.learn.models.shapes.static_shapes` the
    boolean indexing (a data-dependent shape) would break the graph or wait for the
    device, so there :func:`embed_all` computes the same values.
    """
    if not shapes_from_data():
        return embed_all(embed, nodes, mask)
    present = embed(nodes[mask])  # (P, E)
    out = present.new_zeros(*mask.shape, present.shape[-1])  # (M, K, E)
    out[mask] = present
    return out


def embed_all(embed: torch.nn.Module, nodes: Tensor, mask: Tensor) -> Tensor:
    """:func:`embed_present` without data-dependent shapes: embed every slot, zero the padding.

    Same values and gradients (up to float rounding of differently sized
    matrix products); more arithmetic, but one static graph for the compiler. The
    padding is zeroed before the embedding too: a NaN there would reach the weight
    gradients (0 x NaN) even though ``where`` drops it from the output.
    """
    present = mask[..., None]  # (M, K, 1)
    return torch.where(present, embed(nodes.masked_fill(~present, 0.0)), 0.0)  # (M, K, E)
