"""Allocator policy of the trainer: keep freed memory in the process.

The PPO update allocates and frees the same few hundred tensors of 0.1-4 MB
every minibatch. glibc's ``malloc`` serves blocks that large with ``mmap`` and
hands them back to the kernel on ``free`` (and trims the heap top), so every
minibatch page-faults its working set in again, one 4 KiB page at a time, and
the kernel zeroes each page: about 7,000 minor faults and a fifth of the
update's CPU time went to that (``benchmarks/results/learner-x3/``).
Raising the mmap threshold and the trim threshold keeps those blocks on the
heap for reuse: the faults drop to about 50 per minibatch and the numbers
computed are the same.

The cost is that the process keeps its peak heap until it exits, which is
what a trainer does anyway. Only glibc has ``mallopt``; elsewhere (macOS,
musl) this does nothing and says so once in the log.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging

log = logging.getLogger("diacc")

#: ``mallopt`` parameters (glibc's malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
#: Largest mmap threshold glibc accepts on 64-bit (HEAP_MAX_SIZE / 2): blocks up to
#: this size come from the heap; larger ones (rare in the update) are still mapped.
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
#: Free heap top kept before it is trimmed back to the kernel.
TRIM_THRESHOLD_BYTES = 1 << 30

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Apply the policy in this process (once); True if glibc took both settings."""
    global _applied
    if _applied is not None:
        return _applied
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        log.debug("allocator policy not applied: no glibc mallopt in this C library")
        _applied = False
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # The mmap threshold first: setting the trim threshold alone switches off glibc's
    # dynamic mmap threshold and makes every large block a fresh mapping (3x the faults).
    _applied = bool(
        mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        and mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
    return _applied
