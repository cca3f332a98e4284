"""A cast's chunks shared between this process and one forked helper process (``lrfsim.cast.scans.cast_scans(...,
threads=Forked(...))``), for a cast whose chunks hold the GIL most of their time.

Why a process: the threads of lrfsim.cast.scans overlap only inside ``mj_multiRay`` (which releases the GIL). A cast
of many short calls, such as `lrfsim plan`'s sparse "edges" cast (tunnel_v: 28,000 calls of 31 rays on average, a
third of its time in ``mj_multiRay``), spends the rest in numpy on small arrays and in Python, under the GIL: two
threads cast it no faster than one (measured: docs/speed.md, "plan"). A forked helper has a GIL of its own.

How: the chunks' output arrays are allocated in memory shared with the helper (:func:`shared_empty`) before it is
forked; it inherits everything else (the scene, its MjData, the motor angles) by the fork. Both processes claim
chunks one at a time from a pipe holding their indices (a read of 4 bytes takes one, atomically), so the faster
one takes more; the helper sends back the stats of its chunks (pickled) and exits. Each chunk writes only its own
scans, by the same arithmetic in either process: the cast is bit-identical to one in this process
(tests/test_plan_speed.py). ``Forked.meanwhile`` runs in this process once the helper has started, before it claims
chunks (`lrfsim plan` imports the prediction's modules there, while the helper casts).

Where no helper can be forked (no fork on this platform, one core, too many chunks for the pipe) the chunks run in
this process; where the helper dies or fails, or is stuck (no answer HELPER_PATIENCE_S plus HELPER_PATIENCE_RATIO
times this process's casting time after this process is done: it is ended), the chunks it claimed and did not
report run here again: the same outcome, only slower (an error a chunk raises is raised here). Nothing is written to
disk.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import pickle
import select
import signal
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from lrfcal import cores

T = TypeVar("T")

#: the most chunks whose indices fit the claim pipe's buffer (64 KiB on Linux, 4 bytes per chunk) with room to spare
MAX_CHUNKS = 8192
#: once this process has cast its chunks, the helper gets this long plus HELPER_PATIENCE_RATIO times this process's
#: casting time to send its own (else it is taken for stuck: ended, its chunks cast here)
HELPER_PATIENCE_S = 30.0
HELPER_PATIENCE_RATIO = 10.0


@dataclass(frozen=True)
class Forked:
    """Cast the chunks in this process and one forked helper process (module docstring). ``meanwhile()``: run in
    this process while the helper starts casting (where there is no helper: before the cast)."""

    meanwhile: Callable[[], object] | None = None


def can_fork(n_chunks: int) -> bool:
    """Whether a helper process is worth forking for ``n_chunks`` chunks: Linux, two cores or more, at least two
    chunks and at most MAX_CHUNKS."""
    return sys.platform.startswith("linux") and hasattr(os, "fork") and cores() >= 2 and 2 <= n_chunks <= MAX_CHUNKS


def shared_empty(shape: tuple[int, ...], fill: float | None = None) -> NDArray[np.float64]:
    """A float64 array of ``shape`` in anonymous memory shared with the processes forked after it (``fill``: its
    value, else uninitialised as np.empty; the memory is zeroed by the system)."""
    n = int(np.prod(shape, dtype=np.int64))
    buf = mmap.mmap(-1, max(8, 8 * n))  # MAP_SHARED | MAP_ANONYMOUS: written by the helper, read here
    a = np.frombuffer(buf, dtype=np.float64, count=n).reshape(shape)
    if fill is not None and fill != 0.0:
        a.fill(fill)
    return a


def run_forked(run: Callable[[int], T], n_chunks: int, meanwhile: Callable[[], object] | None = None) -> list[T]:
    """``run(i)`` for i in range(n_chunks), shared between this process and a forked helper (module docstring);
    their values in order. ``run`` must write its results into memory from :func:`shared_empty` (the helper's other
    writes are its own) and return something picklable."""
    if not can_fork(n_chunks):
        if meanwhile is not None:
            meanwhile()
        return [run(i) for i in range(n_chunks)]
    claim_r, claim_w = os.pipe()
    back_r, back_w = os.pipe()
    try:
        os.write(claim_w, struct.pack(f"<{n_chunks}i", *range(n_chunks)))
    finally:
        os.close(claim_w)  # the helper sees the end of the indices when both have read them all
    pid = -1
    try:
        try:
            pid = os.fork()
        except OSError:  # no helper could be forked: every chunk runs here
            pid = -1
        if pid == 0:  # the helper: never returns
            _helper(run, claim_r, back_r, back_w)
        os.close(back_w)
        back_w = -1
        if meanwhile is not None:
            meanwhile()
        t0 = time.monotonic()
        mine = _claim(run, claim_r)
        # a helper that is this much slower than this process is stuck (a fork can inherit a lock that another
        # thread held): ended, and its chunks cast here
        patience = HELPER_PATIENCE_S + HELPER_PATIENCE_RATIO * (time.monotonic() - t0)
        theirs = _collect(back_r, pid, patience) if pid > 0 else {}
        pid = -1
    finally:
        for fd in (claim_r, back_r, back_w):
            if fd >= 0:
                os.close(fd)
        if pid > 0:  # an error here (Ctrl-C too): the helper works for nothing
            with contextlib.suppress(OSError):  # (already ended and reaped)
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
    done = {**theirs, **mine}
    return [done[i] if i in done else run(i) for i in range(n_chunks)]  # the helper's unreported chunks: here


def _claim(run: Callable[[int], T], claim_r: int) -> dict[int, T]:
    """Claim chunks from the pipe and run them until none is left."""
    out: dict[int, T] = {}
    while len(b := os.read(claim_r, 4)) == 4:
        i = struct.unpack("<i", b)[0]
        out[i] = run(i)
    return out


def _helper(run: Callable[[int], Any], claim_r: int, back_r: int, back_w: int) -> None:
    """The forked helper: claim and run chunks, send their values back, exit (never returns to the caller)."""
    code = 1
    try:  # Ctrl-C reaches it too: a KeyboardInterrupt ends it like any error
        os.close(back_r)
        data = pickle.dumps(_claim(run, claim_r), protocol=pickle.HIGHEST_PROTOCOL)
        view = memoryview(data)
        while view:
            view = view[os.write(back_w, view):]
        code = 0
    except BaseException:  # noqa: BLE001 - the parent runs the unreported chunks itself and sees any error there
        pass
    finally:
        os._exit(code)  # no atexit handlers, no flushing of the parent's buffered output


def _collect(back_r: int, pid: int, patience_s: float) -> dict[int, Any]:
    """The helper's values by chunk (empty where it died, failed or sent nothing within ``patience_s``: then it is
    ended), once it has exited."""
    parts = []
    deadline = time.monotonic() + patience_s
    while True:
        ready, _, _ = select.select([back_r], [], [], max(0.0, deadline - time.monotonic()))
        if not ready:  # stuck: ended, its chunks cast here
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return {}
        chunk = os.read(back_r, 1 << 16)
        if not chunk:
            break
        parts.append(chunk)
    _, status = os.waitpid(pid, 0)
    if os.waitstatus_to_exitcode(status) != 0 or not parts:
        return {}
    try:
        return dict(pickle.loads(b"".join(parts)))
    except Exception:  # noqa: BLE001 - a truncated message: its chunks run here
        return {}


__all__ = ["MAX_CHUNKS", "Forked", "can_fork", "run_forked", "shared_empty"]
