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
(lrfcal.io.cliutil.Command.invoke, ``lrfsim study``'s process-pool workers). A user who sets NUMPY_MADVISE_HUGEPAGE
keeps
their choice. A library call leaves the process as it is.
"""

from __future__ import annotations

import os

#: numpy's environment variable for the same switch; when set, its value stands
NUMPY_ENV_VAR = "NUMPY_MADVISE_HUGEPAGE"


def apply_memory_policy() -> bool:
    """numpy's huge-page madvise off for this process (module docstring), unless :data:`NUMPY_ENV_VAR` is set or
    this numpy has no such switch. Returns whether the policy was applied."""
    if os.environ.get(NUMPY_ENV_VAR) is not None:
        return False
    try:
        from numpy._core.multiarray import _set_madvise_hugepage
    except ImportError:  # numpy < 2 named its core module numpy.core
        try:
            from numpy.core.multiarray import _set_madvise_hugepage
        except ImportError:
            return False
    _set_madvise_hugepage(False)
    return True


__all__ = ["NUMPY_ENV_VAR", "apply_memory_policy"]
