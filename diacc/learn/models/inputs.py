"""The single place where numpy observation containers become torch tensors.

Every network takes a ``dict[str, Tensor]`` keyed by the container's field
names. Floats become float32, booleans stay bool (masks), integers become int64
(action indices, neighbour indices), so that no model has to guess dtypes.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import Tensor

from diacc.envs.observation import ActorObs, CriticState
from diacc.learn.models.errors import ModelError
from diacc.records import Batched

TensorDict = dict[str, Tensor]


def to_tensors(
    container: ActorObs | CriticState | Mapping[str, np.ndarray],
    device: str | torch.device = "cpu",
) -> TensorDict:
    """Convert an observation container (any leading batch axes) to tensors on ``device``.

    Unmasked neighbour indices of a critic state are checked to lie inside the
    node axis here, once per conversion, instead of inside every forward pass.
    """
    if isinstance(container, Batched):
        arrays = container.arrays()
    elif isinstance(container, Mapping):
        arrays = dict(container)
    else:
        raise ModelError(
            f"to_tensors expects ActorObs, CriticState or a dict, got {type(container)}"
        )
    out: TensorDict = {}
    for name, value in arrays.items():
        array = np.asarray(value)
        if array.dtype == np.bool_:
            tensor = torch.from_numpy(np.ascontiguousarray(array))
        elif np.issubdtype(array.dtype, np.floating):
            tensor = torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))
        elif np.issubdtype(array.dtype, np.integer):
            tensor = torch.from_numpy(np.ascontiguousarray(array, dtype=np.int64))
        else:
            raise ModelError(f"observation field {name!r} has unsupported dtype {array.dtype}")
        out[name] = tensor.to(device)
    if "neighbours" in arrays and "neighbour_mask" in arrays:
        _check_neighbour_range(
            np.asarray(arrays["neighbours"]), np.asarray(arrays["neighbour_mask"])
        )
    return out


def _check_neighbour_range(neighbours: np.ndarray, mask: np.ndarray) -> None:
    n_nodes = neighbours.shape[-2]
    bad = mask & ((neighbours < 0) | (neighbours >= n_nodes))
    if bad.any():
        raise ModelError(f"{int(bad.sum())} unmasked neighbour indices lie outside [0, {n_nodes})")


def merge_leading(tensors: Mapping[str, Tensor], n_axes: int) -> TensorDict:
    """Merge the first ``n_axes`` axes of every tensor into one (e.g. (T, B, ...) -> (T*B, ...))."""
    return {k: v.reshape(-1, *v.shape[n_axes:]) for k, v in tensors.items()}


def require(
    tensors: Mapping[str, Tensor], keys: tuple[str, ...], batch_shape: tuple[int, ...], owner: str
) -> None:
    """Raise :class:`ModelError` if a key is missing or a tensor's leading axes differ."""
    missing = [k for k in keys if k not in tensors]
    if missing:
        raise ModelError(f"{owner} input lacks fields {missing}")
    n = len(batch_shape)
    for k in keys:
        if tuple(tensors[k].shape[:n]) != batch_shape:
            raise ModelError(
                f"{owner} input {k!r} has leading shape {tuple(tensors[k].shape[:n])}, "
                f"expected {batch_shape}"
            )
