"""Batches of trials on a local process pool, counted as each trial finishes (not as each batch does).

Every worker gets, at its start, a queue (a ``multiprocessing`` queue can only be handed over then, as the pool's
``initargs``) on which :func:`tick` puts one item per finished trial; the calling process counts them while it
waits for the batches, so a batch of many trials does not show 0/N until it returns.

What every batch needs and is the same for all of them (a study's shared cast: 51 MB for tunnel_v) is handed to
each worker once, at its start, too (:func:`worker_held`): with the ``fork`` start method it is inherited, not
pickled at all, where a task's arguments are pickled for every batch. Batches can then be small (a study sends one
trial each), handed out as workers free up: no core waits at the end for a worker that drew the longer batch.
"""

from __future__ import annotations

import multiprocessing
import queue as queue_module
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, TypeVar

T = TypeVar("T")

#: the queue of finished trials in a worker process (set by :func:`_worker_start`)
_FINISHED: Any = None
#: what the calling process handed to every worker at its start (set by :func:`_worker_start`)
_HELD: dict[str, Any] = {}
#: how long the calling process waits for a finished trial before it looks at the batches again [s]
POLL_S = 0.2
#: how long it waits for a finished trial's item once every batch has returned [s]
DRAIN_S = 2.0


def _worker_start(finished: Any, initializer: Callable[[], None], held: dict[str, Any]) -> None:
    global _FINISHED, _HELD
    _FINISHED, _HELD = finished, held
    initializer()


def worker_held() -> dict[str, Any]:
    """In a worker of :func:`run_counted`: the ``held`` mapping the calling process handed over, this worker's own
    copy (a task may keep what it builds there for the worker's next batches); ``{}`` elsewhere."""
    return _HELD


def tick(_done_in_batch: int) -> None:
    """A batch's progress callback in a worker: one trial finished (put on the queue of :func:`run_counted`)."""
    if _FINISHED is not None:
        _FINISHED.put(1)


def run_counted(task: Callable[..., list[T]], batches: Sequence[Any], workers: int,
                initializer: Callable[[], None], progress: Callable[[int], None] | None, *,
                held: dict[str, Any] | None = None, meanwhile: Callable[[], None] | None = None) -> list[list[T]]:
    """``task(batch, progress=tick)`` for every batch on a pool of ``workers`` processes (each started with
    ``initializer``, holding ``held``: :func:`worker_held`), handed out in order as workers free up;
    ``progress(done)`` in this process after every finished trial (``done``: trials finished so far, in any batch).
    ``meanwhile()`` runs in this process once the workers have started (the trials' progress is counted after it).
    Returns the batches' results in the order of ``batches``; a batch's exception is raised here, as
    ``ProcessPoolExecutor.map`` would; an exception of ``meanwhile`` cancels the batches not started yet."""
    ctx = multiprocessing.get_context()
    finished = ctx.Queue()
    done, expected = 0, sum(len(b) for b in batches)
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_start,
                             initargs=(finished, initializer, held or {})) as pool:
        futures = [pool.submit(task, b, progress=tick) for b in batches]
        if meanwhile is not None:
            try:
                meanwhile()
            except BaseException:
                pool.shutdown(wait=True, cancel_futures=True)
                raise
        while done < expected:
            running = not all(f.done() for f in futures)
            try:  # after the last batch, what a worker put last may still be on its way: waited for, briefly
                finished.get(timeout=POLL_S if running else DRAIN_S)
            except queue_module.Empty:
                if not running:
                    break  # a batch that failed: its exception is raised below
                continue
            done += 1
            if progress is not None:
                progress(done)
        results = [f.result() for f in futures]
    finished.close()
    return results


__all__ = ["DRAIN_S", "POLL_S", "run_counted", "tick", "worker_held"]
