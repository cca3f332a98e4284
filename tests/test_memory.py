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
    before = ("from lrfcal.runtime.memory import apply_memory_policy\napplied = apply_memory_policy()\n"
              + code.replace("applied = apply_memory_policy()\n", ""))  # the policy applied before numpy loads
    early = fresh_python(before, unset="NUMPY_MADVISE_HUGEPAGE")
    assert early.stdout.split() == ["True", "False"], early.stderr  # numpy loaded with the switch off


def test_keep_freed_memory_reuses_large_blocks_without_page_faults() -> None:
    """With keep_freed_memory (lrfsim study's trial processes), three 13 MB arrays made and dropped over and over
    are served from what the process freed: (almost) no page faults, where glibc's default returns them to the
    kernel and faults them in anew; a user's glibc malloc setting stands. Fresh interpreters: the setting is the
    process's."""
    import pytest

    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's mallopt: Linux only")
    code = ("import resource, numpy as np\n"
            "from lrfcal.runtime.memory import keep_freed_memory\n"
            "import sys\napplied = keep_freed_memory() if sys.argv[1:] == ['keep'] else None\n"
            "def blocks():\n    a = [np.ones(13 << 17) for _ in range(3)]\n    del a\n"
            "blocks()\nf = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
            "for _ in range(10):\n    blocks()\n"
            "print(applied, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f)")

    def run(*args: str, **env: str) -> list[str]:
        base = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
        out = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True,
                             env={**base, **env}, timeout=120)
        return out.stdout.split() or [out.stderr]

    applied, kept = run("keep")
    if applied != "True":
        pytest.skip("the C library is not glibc (mallopt refused)")
    _, default = run("default")
    pages = 10 * 3 * (13 << 20) // 4096  # the pages of 30 arrays
    assert int(kept) < 0.01 * pages < 0.05 * pages < int(default), (kept, default)  # 0 and 10,000-15,000 here
    assert run("keep", MALLOC_TRIM_THRESHOLD_="131072")[0] == "False"  # the user's setting stands
