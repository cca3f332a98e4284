"""The BLAS / OpenMP thread policy of the command-line programs and of the worker processes they start.

The calibration's matrix products are small (Jacobians of a few thousand rows by 10-20 columns, 11 x 11 normal
equations): a BLAS that starts a thread per core inside each of them gains nothing on a quiet machine and loses
badly on a busy one, where every product waits for threads that other processes keep off the cores (issue 19: a
targetless calibration took 312 s with OpenBLAS's default threads at load 4-5 on 2 cores, 47 s with one thread).
So the programs run BLAS and OpenMP with :data:`DEFAULT_THREADS` thread(s) per process; measured quiet and loaded
by benchmarks/bench_threads.py (docs/speed.md, "Threads").

Where the policy applies (one function each, used by every entry point):

* :func:`apply_thread_policy`: for the whole process; called by every command of ``lrfcal`` and ``lrfsim`` when
  it starts (lrfcal.terminal.cliutil.Command.invoke: not for ``--help`` or a usage error) and as the initializer of
  ``lrfsim study``'s process-pool workers;
* :func:`thread_policy`: a context manager that restores the previous limits on exit; ``lrfsim study`` runs every
  batch it sends to a dask worker in it (:func:`call_with_thread_policy`: a cluster's workers are not ours to
  change for good);
* :func:`one_blas_thread`: one BLAS thread whatever the policy, for work spread over threads of its own (the
  simulator's cast).

A library call (``lrfcal.pipeline.calibrate``, ``lrfsim.simulate.simulate``, ...) leaves the caller's thread
settings as they are; wrap it in :func:`thread_policy` to get the programs' behaviour.

The environment variable :data:`ENV_VAR` overrides the number of threads (a positive integer, or ``default`` for
the libraries' own choice), e.g. to measure the policy: ``LRF_CALIB_BLAS_THREADS=default lrfcal calibrate ...``.

threadpoolctl only reaches the libraries loaded when it is called: :func:`apply_thread_policy` limits those and sets
the variables the libraries read when they load (:data:`LIBRARY_ENV`) for the rest; :func:`thread_policy`, which
restores the limits it found, imports numpy and scipy.linalg (each ships its own OpenBLAS) first.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from lrfcal.errors import InputError

T = TypeVar("T")

#: BLAS / OpenMP threads per process of the programs and their workers (measured; module docstring).
DEFAULT_THREADS = 1
#: Environment variable overriding :data:`DEFAULT_THREADS`: a positive integer or ``default`` (no limit set).
ENV_VAR = "LRF_CALIB_BLAS_THREADS"


def policy_threads() -> int | None:
    """The number of BLAS / OpenMP threads per process: :data:`ENV_VAR` if set, else :data:`DEFAULT_THREADS`;
    None for ``default`` (leave the libraries' own choice).

    Raises:
        InputError: :data:`ENV_VAR` is neither a positive integer nor ``default``.
    """
    text = os.environ.get(ENV_VAR, "").strip()
    if not text:
        return DEFAULT_THREADS
    if text.lower() == "default":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise InputError(f"{ENV_VAR}: expected a positive number of threads or 'default', got {text!r}")
    return n


def _load_libraries() -> None:
    """Import the modules that load a BLAS, so that threadpoolctl finds them (module docstring)."""
    import numpy  # noqa: F401
    from scipy import linalg  # noqa: F401


#: The environment variables the BLAS and OpenMP libraries read when they are loaded (OpenBLAS, which numpy's and
#: scipy's wheels ship, reads OPENBLAS_NUM_THREADS in its constructor; libgomp OMP_NUM_THREADS; MKL, BLIS and
#: Apple's Accelerate their own).
LIBRARY_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS")


def apply_thread_policy() -> int | None:
    """Limit every BLAS and OpenMP library of this process to :func:`policy_threads` threads, for good (the
    programs' entry points and worker initializers): those loaded already through threadpoolctl, those loaded later
    (and the process's children) through the variables they read when they load (:data:`LIBRARY_ENV`), so that
    nothing is imported for the policy's sake: a command that ends on bad input answers before numpy or scipy is
    loaded. Returns the limit (None: left as it was)."""
    n = policy_threads()
    if n is not None:
        os.environ.update(dict.fromkeys(LIBRARY_ENV, str(n)))
        if "numpy" in sys.modules or "scipy" in sys.modules:
            from threadpoolctl import threadpool_limits

            threadpool_limits(limits=n)
    return n


@contextmanager
def thread_policy() -> Iterator[int | None]:
    """Within the block, every loaded BLAS and OpenMP library runs :func:`policy_threads` threads; the previous
    limits are restored on exit. Yields the limit (None: left as it was)."""
    n = policy_threads()
    if n is None:
        yield None
        return
    from threadpoolctl import threadpool_limits

    _load_libraries()
    with threadpool_limits(limits=n):
        yield n


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Within the block, BLAS runs one thread whatever the policy (the previous limits restored on exit): for work
    that is itself spread over threads (lrfsim.raycast's chunks), whose matrix products would otherwise each start
    BLAS threads of their own and wait for each other (a 2-thread cast 2.8 s against 1.8 s on tunnel_v)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def call_with_thread_policy(fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> T:
    """``fn(*args, **kwargs)`` within :func:`thread_policy` (a task sent to a worker that is not ours)."""
    with thread_policy():
        return fn(*args, **kwargs)


__all__ = ["DEFAULT_THREADS", "ENV_VAR", "LIBRARY_ENV", "apply_thread_policy", "call_with_thread_policy",
           "one_blas_thread", "policy_threads", "thread_policy"]
