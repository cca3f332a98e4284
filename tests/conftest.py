"""Session-wide fixtures shared by the test modules.

``recording_of(scenario)``: the recording folder of a scenario, simulated and written once per test run and shared
by every test module that asks for the same scenario (the simulation is seeded, so the same scenario gives the same
recording). Under pytest-xdist every worker is its own session: the folders live beside the workers' temporary
folders, and the first worker that needs one simulates it while the others wait on a file lock. Tests read these
folders; one that changes a recording copies it first.

The tests run BLAS with the programs' thread policy (lrfcal.runtime.threads), as the console scripts do: one thread per
process, so two test workers on two cores do not oversubscribe them.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from lrfcal.runtime.memory import apply_memory_policy
from lrfcal.runtime.threads import apply_thread_policy
from lrfsim.scenario import Scenario, load_scenario

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def pytest_configure(config: pytest.Config) -> None:
    apply_memory_policy()  # the programs' policies, in every worker (lrfcal.runtime.memory, lrfcal.runtime.threads)
    apply_thread_policy()


def group_of(nodeid: str) -> str:
    """The group of a test (``tests/test_x.py::test_y[param]``): the tests of one group run on one worker, in order,
    so that a module's fixtures are built once. A group is the test's module, except where the longest modules are
    split and no fixture is shared (recordings are: on disk, below): test_recovery into its random truths and its
    shipped scenarios, test_targetless into its tests (the two on the real box share theirs), test_trust into its
    tests."""
    path, _, name = nodeid.partition("::")
    module = Path(path).stem
    if module == "test_recovery" and "shipped" in name:
        return "test_recovery_shipped"
    if module == "test_targetless" and "real_urg04lx" not in name or module == "test_trust":
        return f"{module}::{name}"
    return module


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: object) -> object:
    """Under ``pytest -n N --dist loadscope`` (pyproject's addopts) the scope of a test is its :func:`group_of`.
    (This replaces ``--dist loadgroup`` with xdist_group marks, which pytest 9.2 silently broke: xdist 3.8 writes the
    group into the node id, which pytest 9.2 no longer reads: pytest-dev/pytest-xdist#1386.)"""
    if config.getvalue("dist") != "loadscope":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Groups(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid)

    return Groups(config, log)  # type: ignore[arg-type]


@contextmanager
def _locked(path: Path) -> Iterator[None]:
    """An exclusive lock on ``path`` (created) between the processes of this test run."""
    with path.open("a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def _shared_root(factory: pytest.TempPathFactory) -> Path:
    """A folder every worker of this run sees: beside the workers' base folders under xdist, else inside ours."""
    base = factory.getbasetemp()
    root = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "shared-recordings"
    root.mkdir(parents=True, exist_ok=True)
    return root


@pytest.fixture(scope="session")
def recording_of(tmp_path_factory: pytest.TempPathFactory) -> Callable[[Scenario], Path]:
    """``recording_of(scenario)`` -> its recording folder (module docstring); do not write into it."""
    from lrfsim.simulate import simulate, write_recording

    root = _shared_root(tmp_path_factory)

    def get(scenario: Scenario) -> Path:
        key = hashlib.sha256(scenario.model_dump_json().encode()).hexdigest()[:16]
        folder = root / f"{scenario.name}-{key}"
        with _locked(root / f"{folder.name}.lock"):
            if not folder.is_dir():  # written atomically: a folder that exists is complete
                write_recording(simulate(scenario), scenario, folder)
        return folder

    return get


@pytest.fixture(scope="session")
def shipped_recording(recording_of: Callable[[Scenario], Path]) -> Callable[[str], Path]:
    """``shipped_recording(name)`` -> the recording folder of scenarios/<name>.yaml (shared, read-only)."""
    return lambda name: recording_of(load_scenario(SCENARIOS / f"{name}.yaml"))
