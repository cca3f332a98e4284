"""Batches of trials on a local process pool, counted as each trial finishes (not as each batch does).

A study cuts its trials into one batch per worker (each batch builds the scene once), so counting finished
batches shows 0/N for almost the whole run. Here every worker gets, at its start, a queue (a
``multiprocessing`` queue can only be handed over then, as the pool's ``initargs``) on which :func:`tick` puts
one item per finished trial; the calling process counts them while it waits for the batches.
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
#: how long the calling process waits for a finished trial before it looks at the batches again [s]
POLL_S = 0.2
#: how long it waits for a finished trial's item once every batch has returned [s]
DRAIN_S = 2.0


def _worker_start(finished: Any, initializer: Callable[[], None]) -> None:
    global _FINISHED
    _FINISHED = finished
    initializer()


def tick(_done_in_batch: int) -> None:
    """A batch's progress callback in a worker: one trial finished (put on the queue of :func:`run_counted`)."""
    if _FINISHED is not None:
        _FINISHED.put(1)


def run_counted(task: Callable[..., list[T]], batches: Sequence[Any], workers: int,
                initializer: Callable[[], None], progress: Callable[[int], None] | None) -> list[list[T]]:
    """``task(batch, progress=tick)`` for every batch on a pool of ``workers`` processes (each started with
    ``initializer``); ``progress(done)`` in this process after every finished trial (``done``: trials finished so
    far, in any batch). Returns the batches' results in the order of ``batches``; a batch's exception is raised
    here, as ``ProcessPoolExecutor.map`` would."""
    ctx = multiprocessing.get_context()
    finished = ctx.Queue()
    done, expected = 0, sum(len(b) for b in batches)
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_start,
                             initargs=(finished, initializer)) as pool:
        futures = [pool.submit(task, b, progress=tick) for b in batches]
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


__all__ = ["DRAIN_S", "POLL_S", "run_counted", "tick"]
