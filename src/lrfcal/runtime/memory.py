"""The memory policy of the command-line programs and of the worker processes they start: numpy's large arrays on
ordinary pages, not transparent huge pages.

numpy asks the kernel for transparent huge pages (madvise MADV_HUGEPAGE) on every array of 4 MiB or more. Where
the kernel's THP defrag setting is ``madvise`` (the default of many distributions: /sys/kernel/mm/
transparent_hugepage/defrag), each such array's first touch may stall in direct compaction until 2 MiB of
contiguous memory is free, and on a busy or fragmented machine that costs more than the array's whole use. On the
2-core virtual machine of the benchmarks (THP ``madvise``, defrag ``madvise``), with numpy's default:

* the in-process calibration of tunnel_v (``lrfcal.pipeline.calibrate``, its first call in a process as every
  command makes it) took 1.42-2.01 s, 0.7-1.5 s of it in the kernel; without the madvise 0.86-0.98 s (6 runs each,
  alternated);
* ``lrfsim simulate scenarios/tunnel_v.yaml`` took 4.7-5.8 s against 3.1-3.4 s, ``lrfcal calibrate`` 3.2-3.8 s
  against 2.1-2.7 s (3 runs each).

:func:`apply_memory_policy` turns numpy's madvise off for the process (numpy's own switch, which its environment
variable NUMPY_MADVISE_HUGEPAGE sets at import); the programs call it before any work
(lrfcal.terminal.cliutil.Command.invoke, ``lrfsim study``'s process-pool workers). A user who sets
NUMPY_MADVISE_HUGEPAGE keeps
their choice. A library call leaves the process as it is.

A process that allocates and frees the same large arrays over and over (a study's trials: tunnel_v's 13 MB arrays of
(scans, beams), written, read and calibrated 40 times in a worker) can also keep what it frees:
:func:`keep_freed_memory` has glibc's malloc serve blocks up to 32 MiB from its heap and keep up to 1 GiB freed there
(mallopt M_MMAP_THRESHOLD, M_TRIM_THRESHOLD; glibc's own default moves the first limit with the sizes it has seen
and returns a heap's free top beyond twice it to the kernel), instead of mapping fresh pages, each faulted in and
zeroed by the kernel at first touch. A study trial of tunnel_v took 30,000-50,000 page faults and 0.06-0.09 s of
system time, about 100 and 0.01 s with it (5 trials in one process, alternated); the memory's peak is the same
(353 MB). ``lrfsim study`` applies it to its trials' processes (its pool workers, and itself for ``-j 1``); a user's
glibc malloc settings (MALLOC_MMAP_THRESHOLD_, MALLOC_TRIM_THRESHOLD_, GLIBC_TUNABLES) stand.
"""

from __future__ import annotations

import ctypes
import importlib
import os
import sys

#: numpy's environment variable for the same switch; when set, its value stands
NUMPY_ENV_VAR = "NUMPY_MADVISE_HUGEPAGE"
#: glibc's environment settings of its malloc; when one is set, :func:`keep_freed_memory` leaves malloc as it is
GLIBC_MALLOC_ENV = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_")
#: mallopt's parameters (glibc malloc.h) and what :func:`keep_freed_memory` sets them to [bytes]: blocks up to
#: 32 MiB (glibc's largest mmap threshold on 64-bit systems) from the heap, and up to 1 GiB kept free there
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
HEAP_BLOCKS_UP_TO = 32 * 1024 * 1024
KEEP_FREE_UP_TO = 1024 * 1024 * 1024


def apply_memory_policy() -> bool:
    """numpy's huge-page madvise off for this process (module docstring), unless :data:`NUMPY_ENV_VAR` is set or
    this numpy has no such switch: numpy's own switch once numpy is loaded, before that the variable numpy reads as
    it loads (so that a command that ends on bad input answers without loading numpy; the process's children
    inherit it). Returns whether the policy was applied."""
    if os.environ.get(NUMPY_ENV_VAR) is not None:
        return False
    if "numpy" not in sys.modules:  # numpy reads the variable as it loads: nothing imported for the policy's sake
        os.environ[NUMPY_ENV_VAR] = "0"
        return True
    for core in ("numpy._core.multiarray", "numpy.core.multiarray"):  # numpy < 2 named its core module numpy.core
        try:
            switch = importlib.import_module(core)._set_madvise_hugepage  # numpy's own, not in its type stubs
        except (ImportError, AttributeError):
            continue
        switch(False)
        return True
    return False


def keep_freed_memory() -> bool:
    """glibc's malloc keeps the large blocks this process frees for its next allocations (module docstring), unless
    a glibc malloc setting is in the environment or the C library is not glibc (mallopt missing or refusing).
    Returns whether it was applied. For processes that repeat the same large allocations (a study's trials)."""
    if any(k in os.environ for k in GLIBC_MALLOC_ENV) or "malloc" in os.environ.get("GLIBC_TUNABLES", ""):
        return False
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library of this process
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, HEAP_BLOCKS_UP_TO)) and bool(mallopt(M_TRIM_THRESHOLD, KEEP_FREE_UP_TO))


__all__ = ["GLIBC_MALLOC_ENV", "NUMPY_ENV_VAR", "apply_memory_policy", "keep_freed_memory"]
