"""The programs' memory policy (lrfcal.runtime.memory)."""

from __future__ import annotations

import os
import subprocess
import sys


def fresh_python(code: str, unset: str, timeout: float = 120, **env: str) -> subprocess.CompletedProcess[str]:
    """``python -c code`` in a fresh interpreter (a process policy is the process's), with the variable ``unset``
    removed from this environment and ``env`` added."""
    base = {k: v for k, v in os.environ.items() if k != unset}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**base, **env},
                          timeout=timeout)


def test_the_memory_policy_keeps_numpys_large_arrays_off_huge_pages() -> None:
    """The programs turn numpy's transparent-huge-page madvise off (lrfcal.runtime.memory: 1.42-2.01 s against
    0.86-0.98 s
    for the in-process calibration of tunnel_v where the kernel compacts memory for them); a user's
    NUMPY_MADVISE_HUGEPAGE stands. Run in a fresh interpreter each: the switch is the process's."""
    code = ("import importlib\n"
            "try:\n    m = importlib.import_module('numpy._core.multiarray')\n"
            "except ImportError:  # numpy < 2\n    m = importlib.import_module('numpy.core.multiarray')\n"
            "from lrfcal.runtime.memory import apply_memory_policy\n"
            "applied = apply_memory_policy()\nprint(applied, m._set_madvise_hugepage(True))")
    ours = fresh_python(code, unset="NUMPY_MADVISE_HUGEPAGE")
    assert ours.stdout.split() == ["True", "False"], ours.stderr  # applied; the switch was off
    users = fresh_python(code, unset="NUMPY_MADVISE_HUGEPAGE", NUMPY_MADVISE_HUGEPAGE="1")
    assert users.stdout.split() == ["False", "True"], users.stderr  # the user's choice stands
