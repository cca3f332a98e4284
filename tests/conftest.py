"""Session-wide fixtures shared by the test modules.

``recording_of(scenario)``: the recording folder of a scenario, simulated and written once per test run and shared
by every test module that asks for the same scenario (the simulation is seeded, so the same scenario gives the same
recording). Under pytest-xdist every worker is its own session: the folders live beside the workers' temporary
folders, and the first worker that needs one simulates it while the others wait on a file lock. Tests read these
folders; one that changes a recording copies it first.

The expensive runs that several modules assert on are done once per session and shared (a session fixture is built
once per xdist worker, so :func:`group_of` puts the tests that share one into one group): ``targetless_calibrated``
(a shipped marker-less scene calibrated targetless and written, for tests/test_targetless.py and
tests/test_start_dependence.py), ``real_inspected`` (``lrfcal inspect`` of a shared real bag through the installed
console script, for tests/test_real_walkthrough.py and tests/test_inspect_dh.py), ``urg_from_the_authors_nominal``
(the real URG-04LX bag calibrated targetless from its authors' nominal with --force, for tests/test_targetless.py and
tests/test_real_walkthrough.py), ``full_sweep_run`` (``lrfsim run`` of the small tunnel's full sweep through the
installed console script, for tests/test_cli_sim.py and tests/test_output_names.py) and ``calibrated_trial`` (a
recording calibrated once per worker for each configuration: tests/test_trust.py's good start on tunnel_fast, which
five of its tests and tests/test_servo_faults.py compare with).

The tests run BLAS with the programs' thread policy (lrfcal.runtime.threads), as the console scripts do: one thread per
process, so two test workers on two cores do not oversubscribe them.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from lrfcal.runtime.memory import apply_memory_policy
from lrfcal.runtime.threads import apply_thread_policy
from lrfsim.scenario.file import Scenario, load_scenario

if TYPE_CHECKING:
    from lrfcal.config import CalibConfig
    from lrfcal.result import CalibrationResult
    from lrfsim.trials.trial import Trial

# The console scripts the tests run (and the xdist workers) cache their bytecode as an installed package does: a
# machine that sets PYTHONDONTWRITEBYTECODE (some CI images do) would otherwise compile the project's modules again in
# every one of the suite's few hundred subprocesses (about 0.1 s of CPU each).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
#: public recordings of real rigs shared beside the project, not part of a clone (../shared/realbags/README.md)
REALBAGS = Path(__file__).resolve().parents[2] / "shared" / "realbags"


def console_script(name: str) -> str:
    """The installed console script ``name`` (next to this interpreter, else on PATH), as a user runs it."""
    here = Path(sys.executable).parent / name
    found = str(here) if here.is_file() else shutil.which(name)
    assert found, f"console script {name} is not installed (pip install -e .)"
    return found


def tiered(values: Iterable[Any], keep: int = 1) -> list[Any]:
    """``values`` for ``pytest.mark.parametrize``: the first ``keep`` in the suite, the rest marked ``slow`` (run with
    ``python -m pytest -m slow``, docs/tests.md): a family of repeats (seeds, scenarios, variants) whose first members
    test the behaviour and whose rest measure its spread, which keeps the suite within CI's 4 minutes."""
    out = []
    for i, v in enumerate(values):
        args = v if isinstance(v, tuple) else (v,)
        out.append(v if i < keep else pytest.param(*args, marks=pytest.mark.slow))
    return out


def pytest_configure(config: pytest.Config) -> None:
    apply_memory_policy()  # the programs' policies, in every worker (lrfcal.runtime.memory, lrfcal.runtime.threads)
    apply_thread_policy()


def group_of(nodeid: str) -> str:
    """The group of a test (``tests/test_x.py::test_y[param]``): the tests of one group run on one worker, in order,
    so that a module's fixtures are built once. A group is the test's module, except where the longest modules are
    split and no fixture is shared (recordings are: on disk, below): test_recovery into its random truths and its
    shipped scenarios, test_targetless into its tests, test_trust into its tests. The tests that share a session
    fixture run together: "real bags" (the real-rig walkthrough, inspect_dh's real URG stand, targetless's real
    box and test_check's real recording: ``real_inspected``, ``urg_from_the_authors_nominal``), "room_box targetless"
    (test_start_dependence, targetless's room_box and test_check's targetless pair: ``targetless_calibrated``) and
    "lrfsim run" (test_cli_sim and test_output_names:
    ``full_sweep_run``)."""
    path, _, name = nodeid.partition("::")
    module = Path(path).stem
    if module == "test_real_walkthrough" or module == "test_inspect_dh" and "real_urg" in name \
            or module == "test_targetless" and "real_urg04lx" in name or module == "test_check" and "real" in name:
        return "real bags"
    if module == "test_start_dependence" or module == "test_targetless" and "room_box" in name \
            or module == "test_check" and "targetless" in name:
        return "room_box targetless"
    if module in ("test_cli_sim", "test_output_names"):
        return "lrfsim run"
    if module == "test_recovery" and "shipped" in name:
        return "test_recovery_shipped"
    if module == "test_targetless" and "real_urg04lx" not in name or module == "test_trust":
        return f"{module}::{name}"
    return module


#: the longest groups, longest first (seconds of their tests summed by :func:`group_of` from `python -m pytest
#: --durations=0` on 2 cores, 2026-12-08): the scheduler hands out groups in collection order, and the longest ones
#: sat late in the alphabet (test_study, test_targetless, test_trust), so one worker ran them alone at the end; handed
#: out first, the two workers end together (a fresh clone's tests, docs/tests.md: 4:17 -> 3:56)
LONGEST_FIRST = ("real bags", "test_study", "test_plan", "room_box targetless", "test_cli_faults",
                 "test_recovery_shipped",
                 "test_targetless::test_tunnel_v_with_its_markers_ignored_beside_the_marker_method", "lrfsim run",
                 "test_servo_faults", "test_randomize", "test_bulk_bags", "test_surfaces", "test_check")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The groups of :data:`LONGEST_FIRST` first, in that order; every other test after them as collected (a stable
    sort: a group's tests keep their order)."""
    rank = {g: i for i, g in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(group_of(item.nodeid), len(rank)))


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
    from lrfsim.simulation.recording import write_recording
    from lrfsim.simulation.simulate import simulate

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


@pytest.fixture(scope="session")
def targetless_calibrated(shipped_recording: Callable[[str], Path], tmp_path_factory: pytest.TempPathFactory
                          ) -> Callable[[str], tuple[Path, Path, CalibrationResult]]:
    """``targetless_calibrated(name)`` -> (recording folder, output folder, result) of scenarios/<name>.yaml's
    recording calibrated targetless by lrfcal.commands.calibrate.calibrate_folder, the function ``lrfcal calibrate REC
    -o OUT --targetless --no-figures`` runs (a refusal raises, as the command exits 3); once per session."""
    from lrfcal.commands.calibrate import calibrate_folder
    from lrfcal.config import CalibConfig

    done: dict[str, tuple[Path, Path, CalibrationResult]] = {}

    def get(name: str) -> tuple[Path, Path, CalibrationResult]:
        if name not in done:
            folder = shipped_recording(name)
            out = tmp_path_factory.mktemp(f"targetless-{name}") / "cal"
            done[name] = folder, out, calibrate_folder(folder, out, config=CalibConfig(targetless=True),
                                                       figures=False)
        return done[name]

    return get


def real_bag(name: str) -> Path:
    """../shared/realbags/<name>.bag, or the test is skipped with the reason."""
    path = REALBAGS / f"{name}.bag"
    if not path.is_file():
        pytest.skip(f"real recording not present at {path} (public bag shared beside the project, not part of a "
                    "clone; ../shared/realbags/README.md)")
    return path


@pytest.fixture(scope="session")
def real_inspected(tmp_path_factory: pytest.TempPathFactory
                   ) -> Callable[[str], tuple[subprocess.CompletedProcess, Path]]:
    """``real_inspected(name)`` -> (the process, its rig file) of ``lrfcal inspect BAG -o rig.yaml`` through the
    installed console script on the real bag ``name`` (skipped when absent); once per session."""
    from test_cli_usage import _run

    done: dict[str, tuple[subprocess.CompletedProcess, Path]] = {}

    def get(name: str) -> tuple[subprocess.CompletedProcess, Path]:
        if name not in done:
            path = real_bag(name)
            rig = tmp_path_factory.mktemp(f"inspect-{name}") / "rig.yaml"
            done[name] = _run("lrfcal", "inspect", path, "-o", rig, timeout=600), rig
        return done[name]

    return get


@pytest.fixture(scope="session")
def urg_from_the_authors_nominal() -> Callable[[str], CalibrationResult]:
    """``urg_from_the_authors_nominal(name)`` -> the real URG-04LX bag ``name`` (skipped when absent) calibrated
    targetless with force (its failed checks recorded, not raised) from the authors' nominal DH
    (tests/test_real_bags.py: URG_NOMINAL, read with URG_SCAN and URG_SERVO, what ``lrfcal inspect`` proposes for
    it); once per session."""
    from test_real_bags import URG_NOMINAL, URG_SCAN, URG_SERVO

    from lrfcal.config import CalibConfig
    from lrfcal.io.bag import read_bag
    from lrfcal.pipeline import calibrate
    from lrfcal.types import Nominal, Recording

    done: dict[str, CalibrationResult] = {}

    def get(name: str) -> CalibrationResult:
        if name not in done:
            data = read_bag(real_bag(name), URG_SCAN, URG_SERVO, warn=lambda _t: None)
            rec = Recording(scans=data.scans, joints=data.joints, tape=None, nominal=Nominal(dh=URG_NOMINAL))
            done[name] = calibrate(rec, CalibConfig(targetless=True, force=True))
        return done[name]

    return get


@pytest.fixture(scope="session")
def full_sweep_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[subprocess.CompletedProcess, Path]:
    """``lrfsim run small.yaml`` through the installed console script, without -o (the folder runs/tunnel_v), in a
    folder of its own: the small tunnel (tests/test_cli_usage.py's _small) on its full +-90 deg sweep at 30 deg/s,
    one pass (it calibrates). (The process, that folder); once per session; do not write into it."""
    import math

    from test_cli_usage import _run, _small

    folder = tmp_path_factory.mktemp("full-sweep-run")
    scen = _small(folder, **{"servo.start_rad": math.pi / 2, "servo.end_rad": -math.pi / 2,
                             "servo.speed_rad_s": math.radians(30.0), "servo.settle_s": 0.2})
    return _run("lrfsim", "run", scen, cwd=folder, timeout=300), folder


@pytest.fixture(scope="session")
def calibrated_trial(recording_of: Callable[[Scenario], Path]) -> Callable[[Scenario, CalibConfig], Trial]:
    """``calibrated_trial(scenario, config)`` -> lrfsim.trials.trial.calibrate_recording(recording_of(scenario), config,
    keep_result=True), once per session (per xdist worker) for each scenario and configuration; do not change it."""
    from lrfsim.trials.trial import calibrate_recording

    done: dict[tuple[str, str], Trial] = {}

    def get(scenario: Scenario, config: CalibConfig) -> Trial:
        key = scenario.model_dump_json(), config.model_dump_json()
        if key not in done:
            done[key] = calibrate_recording(recording_of(scenario), config, keep_result=True)
        return done[key]

    return get
