"""A process pool that survives dead workers: lost tasks are retried, never lost, never hung.

``multiprocessing.Pool`` replaces a worker that dies but silently drops the
task it held, so ``imap`` waits for it forever. ``concurrent.futures``'
:class:`~concurrent.futures.ProcessPoolExecutor` instead notices the death
at once and fails every unfinished future with ``BrokenProcessPool``; what it
lacks is the recovery, which :func:`map_resilient` adds: it starts a fresh
executor and resubmits the unfinished tasks, each at most ``max_attempts``
times in all, logging every restart (:mod:`diacc.runlog`).

At most ``workers`` tasks are in flight, so the tasks charged with an
attempt when a pool breaks are the ones that were running (the executor
cannot say which of them killed its worker). A task whose function raises
is not retried (the error would recur); its error is kept, the other tasks
go on, and :class:`PoolError` reports every failure once all are done. An
interruption (or a consumer that stops early) terminates the workers at once.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from diacc.errors import DiaccError
from diacc.runlog import log

#: Attempts per task (the first run plus retries after a worker died).
MAX_ATTEMPTS = 3


class PoolError(DiaccError, RuntimeError):
    """Some tasks could not be completed; the message is one line."""


def map_resilient(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    workers: int,
    initializer: Callable[..., None] | None = None,
    initargs: tuple = (),
    max_attempts: int = MAX_ATTEMPTS,
    describe: Callable[[Any], str] = repr,
) -> Iterator[tuple[int, Any]]:
    """Yield ``(task index, fn(task))`` in completion order, running ``workers`` spawn processes.

    Raises :class:`PoolError` after the last result if any task failed.
    """
    attempts = [0] * len(tasks)
    queue = list(range(len(tasks)))[::-1]  # next task at the end
    failures: list[str] = []
    while queue:
        executor = ProcessPoolExecutor(
            workers, mp_context=mp.get_context("spawn"), initializer=initializer, initargs=initargs
        )
        running: dict[Future, int] = {}
        broken = False
        try:
            while queue or running:
                while queue and len(running) < workers and not broken:
                    i = queue[-1]
                    try:  # a worker that died since the last wait breaks the pool here
                        future = executor.submit(fn, tasks[i])
                    except BrokenProcessPool:
                        broken = True
                        break
                    queue.pop()
                    attempts[i] += 1
                    running[future] = i
                if not running:
                    break
                done, _ = wait(running, return_when=FIRST_COMPLETED)
                for future in done:
                    i = running.pop(future)
                    try:
                        result = future.result()
                    except BrokenProcessPool:
                        broken = True
                        queue.append(i)
                        continue
                    except Exception as exc:  # noqa: BLE001 - reported with the task
                        failures.append(f"{describe(tasks[i])}: {_one_line(exc)}")
                        continue
                    yield i, result
                if broken and not running:
                    break
        except BaseException:
            # Interrupted (SIGINT/SIGTERM reach the CLI as KeyboardInterrupt) or the
            # consumer stopped: end the workers now. A graceful shutdown would wait
            # for the tasks in flight, and a parent killed meanwhile left them running.
            _terminate_workers(executor)
            raise
        finally:
            executor.shutdown(wait=True, cancel_futures=True)
        if broken:
            retry = [i for i in queue if attempts[i] < max_attempts]
            for i in set(queue) - set(retry):
                failures.append(
                    f"{describe(tasks[i])}: its worker process died {attempts[i]} times"
                )
            queue = sorted(retry, reverse=True)
            log.warning(
                "a worker process died; started a new pool of %d and resubmitted %d task(s)",
                workers,
                len(queue),
            )
    if failures:
        raise PoolError(f"{len(failures)} of {len(tasks)} tasks failed; first: {failures[0]}")


def _terminate_workers(executor: ProcessPoolExecutor, grace_s: float = 5.0) -> None:
    """SIGTERM every worker of ``executor``, then SIGKILL those still alive after ``grace_s``."""
    processes = list((getattr(executor, "_processes", None) or {}).values())
    for proc in processes:
        if proc.is_alive():
            proc.terminate()
    for proc in processes:
        proc.join(grace_s)
        if proc.is_alive():
            proc.kill()
            proc.join()


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
