"""Independent tasks on the machine's cores without pickling their inputs: the first task runs in this process, the
others in forked children, which inherit everything the tasks read (a calibration result, the modules imported).
Only each task's return value travels back (pickled). Used by the check "starts agree" for its other starts
(lrfcal.stages.starts).

Where no child can be forked (no fork on this platform, one core, a daemonic process such as a pool's worker), or
a child dies (e.g. out of memory), its task runs here: the outcome is the same, only slower.

:class:`Ahead` forks one child early, which prepares (imports matplotlib) on another core while this process
calibrates, and later runs the calls sent to it, in order, on their arguments (what it inherited by the fork, such
as the scans, sent by reference): the report's figures, each drawn as soon as what it shows is known, while this
process goes on.

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
    if len(names) < 2 or not _can_fork():
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


def _can_fork() -> bool:
    import multiprocessing

    return (cores() >= 2 and "fork" in multiprocessing.get_all_start_methods()
            and not multiprocessing.current_process().daemon)


class Ahead:
    """A forked child that runs ``prepare()`` at once and, later, the calls ``fn(*args)`` sent to it, one after the
    other in the order sent (:meth:`start`, then :meth:`result` once per call, in the same order; :meth:`call` does
    both): ``fn`` (a module-level function) and ``args`` are pickled to it, its return values pickled back. Objects
    of ``inherit`` (made before the child was forked, and not changed since) travel by reference: the child has its
    own copy already. A context manager: leaving it ends the child (its pipe closed, then terminated if still
    alive).

    Where no child can be forked (:func:`call_forked`'s conditions) or the child dies, a call runs here, after
    ``prepare()``: the same outcome, only slower. The child ignores SIGINT (Ctrl-C reaches this process, which
    ends it) and is not daemonic, so that ``fn`` may fork in turn (:func:`call_forked`). ``nice``: the child's
    niceness is raised by this much (work on idle cores that must not slow this process where the cores are busy:
    :meth:`ready` says which calls it finished)."""

    def __init__(self, prepare: Callable[[], object], inherit: tuple[object, ...] = (), nice: int = 0) -> None:
        self._prepare = prepare
        self._nice = nice
        self._prepared_here = False
        self._inherited = {id(o): o for o in inherit}
        self._conn: Any = None
        self._proc: Any = None
        self._sent = False
        # (fn, args, its bytes' delivery to the child: None when it runs here)
        self._pending: list[tuple[Callable[..., Any], tuple[Any, ...], _Delivery | None]] = []
        self._sender: _Sender | None = None

    def __enter__(self) -> Ahead:
        if _can_fork():
            import multiprocessing

            ctx = multiprocessing.get_context("fork")
            ours, theirs = ctx.Pipe()
            proc = ctx.Process(target=_serve, args=(theirs, ours, self._prepare, self._inherited, self._nice),
                               name="lrfcal-ahead", daemon=False)
            try:
                proc.start()
            except OSError:  # no child could be started: the calls run here
                return self
            theirs.close()
            self._conn, self._proc = ours, proc
            self._sender = _Sender(ours)
        return self

    def start(self, fn: Callable[..., Any], *args: Any) -> None:
        """Send ``fn(*args)`` to the child, which runs it (after the calls sent before) while this process goes on;
        :meth:`result` returns its value."""
        delivery = None
        if self._conn is not None and self._sender is not None:
            try:
                data = _dumps((fn, args), self._inherited)
            except Exception:  # noqa: BLE001 - a call that does not pickle: run here
                self._close()
            else:  # written by the sender thread: a call larger than the pipe's buffer must not wait for the
                # child to read it (it reads once prepared, and once the calls before are done)
                delivery = self._sender.send(data)
                self._sent = True
        self._pending.append((fn, args, delivery))

    @property
    def started(self) -> bool:
        """Whether :meth:`start` sent a call whose :meth:`result` is not yet taken."""
        return bool(self._pending)

    def ready(self) -> bool:
        """Whether the oldest call whose result is not yet taken has finished in the child (its :meth:`result`
        would not wait)."""
        delivery = self._pending[0][2] if self._pending else None
        if delivery is None or not delivery.done.is_set() or not delivery.ok or self._conn is None:
            return False
        try:
            return bool(self._conn.poll())
        except Exception:  # noqa: BLE001 - a child that died: result() runs the call here
            return False

    def result(self) -> Any:
        """The value of the oldest call :meth:`start` sent whose result is not yet taken: from the child, or, where
        there is none or it died, run here after ``prepare()``."""
        if not self._pending:
            raise RuntimeError("Ahead.result() without a call: start(fn, *args) first")
        fn, args, delivery = self._pending.pop(0)
        if delivery is not None and delivery.wait() and self._conn is not None:
            try:
                ok, value = self._conn.recv()
                if ok:
                    return value
            except Exception:  # noqa: BLE001 - a child that died: this call and the later ones run here
                self._close()
        if not self._prepared_here:
            self._prepare()
            self._prepared_here = True
        return fn(*args)

    def call(self, fn: Callable[..., T], *args: Any) -> T:
        """``fn(*args)``, in the child when there is one: :meth:`start`, then :meth:`result` (no other call may be
        waiting for its result)."""
        if self._pending:
            raise RuntimeError("Ahead.call() while a call started before waits for its result()")
        self.start(fn, *args)
        return self.result()

    def _close(self) -> None:
        if self._sender is not None:
            self._sender.stop()  # after the calls sent so far (a child that died fails them at once)
            self._sender = None
        if self._conn is not None:
            self._conn.close()  # the child's recv ends: it exits
            self._conn = None

    def __exit__(self, *exc: object) -> None:
        # a child that was sent no call is at most preparing, and one whose results are not all taken (an error
        # here) works for nothing: both end at once; one that ran all its calls ends with its pipe
        idle = self._sent and not self._pending
        if not idle and self._proc is not None:
            self._proc.terminate()  # a call still being written to it fails at once
        self._close()
        if self._proc is not None:
            self._proc.join(timeout=1.0 if idle else 0.0)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join()
            self._proc = None


class _Delivery:
    """One call's bytes on their way to :class:`Ahead`'s child: ``done`` once written (``ok``) or failed."""

    def __init__(self, data: bytes) -> None:
        import threading

        self.data: bytes | None = data
        self.done = threading.Event()
        self.ok = False

    def wait(self) -> bool:
        """Whether the bytes reached the child's pipe (waits until they are written or failed)."""
        self.done.wait()
        return self.ok


class _Sender:
    """Writes :class:`Ahead`'s calls to the child's pipe in the order sent, in a thread, so that ``Ahead.start``
    returns at once even when a call is larger than the pipe's buffer and the child is not reading yet. The thread
    runs only while there is something to write (no thread stays behind for a later fork to copy)."""

    def __init__(self, conn: Any) -> None:
        import threading

        self._conn = conn
        self._lock = threading.Lock()
        self._queue: list[_Delivery] = []
        self._thread: threading.Thread | None = None  # the one writing, while there is something to write
        self._broken = False

    def send(self, data: bytes) -> _Delivery:
        import threading

        delivery = _Delivery(data)
        with self._lock:
            self._queue.append(delivery)
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="lrfcal-ahead-sender", daemon=True)
                self._thread.start()
        return delivery

    def _run(self) -> None:
        while True:
            with self._lock:
                if not self._queue:
                    self._thread = None
                    return
                delivery = self._queue.pop(0)
            if not self._broken:
                try:
                    self._conn.send_bytes(delivery.data)
                    delivery.ok = True
                except Exception:  # noqa: BLE001 - a child that died: this call and the later ones run here
                    self._broken = True
            delivery.data = None
            delivery.done.set()

    def stop(self) -> None:
        """Return once the calls sent before are written (or failed)."""
        with self._lock:
            thread = self._thread
        if thread is not None:
            thread.join()


_NOT_INHERITED = object()  # (None is an object too: a missing id must not match it)


def _dumps(obj: object, inherited: dict[int, object]) -> bytes:
    """``obj`` pickled, with the objects of ``inherited`` (id -> object) as references to the child's copies."""
    import io
    import pickle

    class ByReference(pickle.Pickler):
        def persistent_id(self, o: object) -> int | None:
            return id(o) if inherited.get(id(o), _NOT_INHERITED) is o else None

    buf = io.BytesIO()
    ByReference(buf, protocol=pickle.HIGHEST_PROTOCOL).dump(obj)
    return buf.getvalue()


def _loads(data: bytes, inherited: dict[int, object]) -> Any:
    """:func:`_dumps` undone in the child, whose ``inherited`` holds its copies under the parent's ids."""
    import io
    import pickle

    class ByReference(pickle.Unpickler):
        def persistent_load(self, pid: Any) -> object:
            return inherited[pid]

    return ByReference(io.BytesIO(data)).load()


def _serve(conn: Any, parents_end: Any, prepare: Callable[[], object], inherited: dict[int, object],
           nice: int = 0) -> None:
    """:class:`Ahead`'s child: prepare, then run the calls sent, in order, until the pipe closes."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice:
        with contextlib.suppress(OSError):
            os.nice(nice)
    parents_end.close()  # the copy forked with this child: else the parent closing its end would not end recv
    with contextlib.suppress(Exception):
        prepare()
    while True:
        try:
            fn, args = _loads(conn.recv_bytes(), inherited)
        except (EOFError, OSError):
            break
        try:
            conn.send((True, fn(*args)))
        except Exception:  # noqa: BLE001 - the caller runs it again itself and sees the error there
            try:
                conn.send((False, None))
            except Exception:  # noqa: BLE001 - the parent is gone
                break
    conn.close()


def on_cores(fn: Callable[..., T], calls: list[tuple[Any, ...]], parallel: bool = True) -> list[T]:
    """``fn(*args)`` for every ``args`` of ``calls``, in order: in threads on the machine's cores when ``parallel``
    (for numpy work on large arrays, which releases the GIL: nothing is forked or pickled), else here in turn."""
    if not parallel or len(calls) < 2 or cores() < 2:
        return [fn(*args) for args in calls]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(len(calls), cores()), thread_name_prefix="lrfcal") as pool:
        return list(pool.map(lambda args: fn(*args), calls))


__all__ = ["Ahead", "call_forked", "cores", "on_cores"]
