"""Independent tasks on the machine's cores without pickling their inputs: the first task runs in this process, the
others in forked children, which inherit everything the tasks read (a calibration result, the modules imported).
Only each task's return value travels back (pickled). Used for the report's figures (lrfcal.figures, issue 19).

Where no child can be forked (no fork on this platform, one core, a daemonic process such as a pool's worker), or
a child dies (e.g. out of memory), its task runs here: the outcome is the same, only slower.

:func:`on_cores` runs numpy work on large arrays (which releases the GIL) in threads instead: the clouds of stage 7
and their geometry, one per DH set.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")

#: the tasks a forked child runs: set just before the fork, read by the child (nothing is pickled)
_PENDING: dict[str, Callable[[], object]] = {}


def cores() -> int:
    """The cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _run_pending(name: str) -> object:
    return _PENDING[name]()


def call_forked(tasks: dict[str, Callable[[], T]]) -> dict[str, T]:
    """Each task's return value by name (module docstring). Tasks should not raise: one that raises in a child
    runs again here."""
    import multiprocessing
    from concurrent.futures import Future, ProcessPoolExecutor

    names = list(tasks)
    if (len(names) < 2 or cores() < 2 or "fork" not in multiprocessing.get_all_start_methods()
            or multiprocessing.current_process().daemon):
        return {n: tasks[n]() for n in names}
    done: dict[str, T] = {}
    _PENDING.clear()
    _PENDING.update(tasks)
    try:
        with ProcessPoolExecutor(max_workers=len(names) - 1, mp_context=multiprocessing.get_context("fork")) as pool:
            futures: dict[str, Future[object]] = {}
            for n in names[1:]:
                try:
                    futures[n] = pool.submit(_run_pending, n)
                except Exception:  # noqa: BLE001 - no child could be started: run here below
                    break
            done[names[0]] = tasks[names[0]]()
            for n, fut in futures.items():
                with contextlib.suppress(Exception):  # a child that died: run here below
                    done[n] = fut.result()  # type: ignore[assignment]
    finally:
        _PENDING.clear()
    return {n: done[n] if n in done else tasks[n]() for n in names}


def on_cores(fn: Callable[..., T], calls: list[tuple[Any, ...]], parallel: bool = True) -> list[T]:
    """``fn(*args)`` for every ``args`` of ``calls``, in order: in threads on the machine's cores when ``parallel``
    (for numpy work on large arrays, which releases the GIL: nothing is forked or pickled), else here in turn."""
    if not parallel or len(calls) < 2 or cores() < 2:
        return [fn(*args) for args in calls]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(len(calls), cores()), thread_name_prefix="lrfcal") as pool:
        return list(pool.map(lambda args: fn(*args), calls))


__all__ = ["call_forked", "cores", "on_cores"]
