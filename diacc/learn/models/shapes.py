"""Whether the networks may choose a tensor's shape from the data (:func:`static_shapes`).

Three places save work by looking at the data: :func:`~diacc.learn.models.layers.embed_present`
embeds only the nodes that exist, :func:`~diacc.learn.models.recurrent.needed_rows`
encodes only the actor rows that reach a loss, and
:func:`~diacc.learn.models.itdr.trim_padded_nodes` cuts the empty vehicle slots. Each
reads the data back to the host to size its result: cheap on the CPU, a wait on a
GPU, and a new shape in every minibatch for a compiler or a CUDA graph. Under
``torch.compile`` and inside :func:`static_shapes` (the static update,
:mod:`diacc.learn.static_update`) they compute the same values at full size instead.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import torch

#: Per thread: the overlapped rollout's forwards (main thread) keep their savings
#: while the static update runs on the learner thread.
_state = threading.local()


@contextmanager
def static_shapes() -> Iterator[None]:
    """Within the block, on this thread, no network sizes a tensor from the data."""
    before = getattr(_state, "static", False)
    _state.static = True
    try:
        yield
    finally:
        _state.static = before


def shapes_from_data() -> bool:
    """True where a network may size a tensor from the data (see the module docstring)."""
    if torch.compiler.is_compiling():  # first: the compiler never reads the thread state
        return False
    return not getattr(_state, "static", False)
