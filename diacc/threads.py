"""Thread policy: how many torch / OpenMP threads each diacc process uses.

torch starts with one intra-op thread per core. On a 2-core machine that made
training several times slower whenever anything else ran (issue 14; the
"thread policy" rows of docs/benchmarks/index.md): an OpenMP thread that
finishes a parallel region spins waiting for the next one, so two spinning
threads and any second process (a SUMO worker, an evaluator, another run)
fight for two cores. diacc therefore sets thread counts itself:

* **trainer** (rollout forwards and the PPO update, one process):
  :func:`default_threads` intra-op threads, i.e. 1 on a machine with <= 2
  cores, else half the cores (at most :data:`MAX_DEFAULT_THREADS`), leaving
  the rest to environment workers and other jobs. ``TrainConfig.torch_threads``
  (> 0) overrides it. One inter-op thread: diacc runs no parallel graphs.
  With ``TrainConfig.overlap`` the trainer runs two Python threads (rollout
  and PPO update); each runs its own torch ops on itself when the intra-op
  count is 1, so on 2 cores the two keep one core each.
* **worker processes** diacc starts (vector-env workers, evaluator workers,
  SUMO workers): 1 torch thread and ``OMP/MKL/OPENBLAS_NUM_THREADS=1`` in
  their environment (:func:`worker_environment`); they step simulators on
  arrays of tens of vehicles, where library threads only add contention.

The rule for more than 2 cores is a choice, not a measurement (diacc's
machines have 2 cores); ``diacc bench --training`` measures the 2-core case.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

#: Cap of the automatic trainer thread count on large machines.
MAX_DEFAULT_THREADS = 8
#: Library thread variables set to 1 in the environment of worker processes.
WORKER_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def default_threads(cores: int | None = None) -> int:
    """Intra-op threads of the trainer: 1 on <= 2 cores, else cores // 2 (capped)."""
    cores = cores or os.cpu_count() or 1
    return 1 if cores <= 2 else min(MAX_DEFAULT_THREADS, cores // 2)


def set_torch_threads(requested: int = 0) -> int:
    """Apply the policy in this process; ``requested`` > 0 overrides the rule.

    Returns the intra-op thread count now in effect. The inter-op pool can be
    sized only before torch first uses it; if that has happened, it is left as
    it is (diacc never submits inter-op work, so its size does not matter).
    """
    import torch  # here, so that simulator-side modules using this file need no torch

    if requested < 0:
        raise ValueError(f"torch threads must be >= 0 (0 = automatic), got {requested}")
    threads = requested or default_threads()
    torch.set_num_threads(threads)
    if torch.get_num_interop_threads() != 1:
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:  # pool already started; harmless, see docstring
            pass
    return torch.get_num_threads()


def worker_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """A copy of ``base`` (default: this process's environment) with one library thread."""
    env = dict(os.environ if base is None else base)
    env.update({name: "1" for name in WORKER_THREAD_VARS})
    return env


@contextmanager
def worker_environment() -> Iterator[None]:
    """Processes started inside this block (``multiprocessing`` spawn) inherit 1-thread settings.

    ``multiprocessing`` has no ``env=`` argument: a spawned child copies
    ``os.environ`` when it starts, so the variables are set for the duration
    of the block and restored afterwards.
    """
    saved = {name: os.environ.get(name) for name in WORKER_THREAD_VARS}
    os.environ.update({name: "1" for name in WORKER_THREAD_VARS})
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
