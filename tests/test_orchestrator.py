"""The method in one place (issue 45 item 3, issue 57 item 1): both ways pass through one loop
(lrfcal.pipeline.loop.estimated), which calls the engine itself on what the ways ask to estimate; the stages build
requests and never solve; the covariance is widened in one place; the servo's sign is applied in one place;
refusals are told apart by their type. Behaviour (the same calibration.yaml as before) is held by the calibration
tests and benchmarks/before_after.py."""

from __future__ import annotations

import ast
import inspect
import textwrap
import traceback
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import yaml

from lrfcal import pipeline
from lrfcal.config import CalibConfig
from lrfcal.errors import CalibrationError, ClockOffsetError, ClockStartError
from lrfcal.estimate import engine
from lrfcal.io.recording import read_recording
from lrfcal.pipeline import loop
from lrfcal.stages.markers import STAGES as MARKER_STAGES
from lrfcal.stages.markers import MarkerWay
from lrfcal.stages.scene import PlaneWay
from lrfcal.stages.targetless import STAGES as PLANE_STAGES
from lrfcal.types import JointStates
from lrfsim.scenario.file import parse_scenario, with_changes

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "lrfcal"
SCENARIOS = ROOT / "scenarios"
#: what a quick calibration of a shipped scenario changes (one pass of the servo, quickly)
QUICK = {"servo.speed_rad_s": 1.0, "servo.passes": 1, "servo.settle_s": 0.05}


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in ``path`` (``from pkg import module`` as pkg.module too)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out += [(node.lineno, node.module), *((node.lineno, f"{node.module}.{a.name}") for a in node.names)]
    return out


def test_no_stage_solves() -> None:
    """No module of the stages imports the engine or a solver: a stage says what to estimate
    (lrfcal.estimate.request) and the orchestrator solves it."""
    bad = [f"{p.relative_to(ROOT)}:{line} {name}" for p in sorted((SRC / "stages").glob("*.py"))
           for line, name in _imports(p) if name in ("lrfcal.estimate.engine", "lrfcal.estimate.solve")]
    assert not bad, "stages that solve:\n" + "\n".join(bad)


def test_the_engine_is_called_by_the_orchestrator_and_the_estimate_only() -> None:
    """Outside lrfcal/estimate (whose checks solve again), only the orchestrator's room (lrfcal/pipeline: the loop
    and the DH search) imports the engine or its front-ends."""
    bad = [f"{p.relative_to(ROOT)}:{line} {name}" for p in sorted(SRC.rglob("*.py"))
           if p.parent.name not in ("estimate", "pipeline")
           for line, name in _imports(p) if name in ("lrfcal.estimate.engine", "lrfcal.estimate.solve")]
    assert not bad, "the engine reached from elsewhere:\n" + "\n".join(bad)


#: the modules that may ask the engine for an estimate: the loop, the DH search, the checks that solve again
ASKERS = {"pipeline/loop.py", "pipeline/search.py", "estimate/checks.py", "estimate/minima.py"}


def _callers_of_the_engine(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every call of the engine (lrfcal.estimate.engine.estimate) from now on, as the module of lrfcal that asked for
    it (the innermost frame outside the engine itself), in this process; one asked for by another module raises
    (in a forked child too: its task then runs again here, and raises here)."""
    callers: list[str] = []
    real = engine.estimate

    def spy(*args: Any, **kwargs: Any) -> engine.Estimate:
        frames = [Path(f.filename) for f in traceback.extract_stack()[:-1]]
        caller = str([f for f in frames if SRC in f.parents and f.name != "engine.py"][-1].relative_to(SRC))
        assert caller in ASKERS, f"the engine asked by {caller}"
        callers.append(caller)
        return real(*args, **kwargs)

    monkeypatch.setattr(engine, "estimate", spy)
    return callers


def _spiked_and_trimmed(rec: Any) -> Any:
    """``rec`` with one encoder spike and the last tenth of its joint states missing (the scans beyond them
    trimmed)."""
    n = rec.joints.stamps_s.size
    positions = rec.joints.positions_rad.copy()
    positions[n // 3] += 0.5  # one encoder spike
    keep = slice(0, int(0.9 * n))  # the last tenth of the joint states missing: the scans beyond them trimmed
    return replace(rec, joints=JointStates(stamps_s=rec.joints.stamps_s[keep], positions_rad=positions[keep],
                                           name=rec.joints.name))


@pytest.mark.parametrize("name", ["plane_30deg", "room_box"])
def test_both_ways_pass_through_the_same_loop(name: str, recording_of: Callable[[Any], Path],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A calibration with markers and a targetless one each run the orchestrator's loop once, with their own way,
    and every solve of either is asked for by that loop, by the DH search it begins ahead, or by a check that solves
    again (lrfcal/estimate's checks and minima): none by a stage. (Quick recordings: one pass of the servo.)

    The targetless one (room_box with an encoder spike and its joint states cut short) keeps its notes in the order
    they were appended before the loop (issue 45): the plane way's own note first, then the orchestrator's on the
    scans (a spike dropped, scans beyond the joint states trimmed), then the way's steps'."""
    targetless = name == "room_box"
    data = yaml.safe_load((SCENARIOS / f"{name}.yaml").read_text())
    folder = recording_of(parse_scenario(with_changes(data, QUICK), name))
    rec = read_recording(folder, require_distances=not targetless)
    ways: list[str] = []
    real = loop.estimated

    def counted(way: Any, proposal: Any) -> Any:
        ways.append(type(way).__name__)
        return real(way, proposal)

    monkeypatch.setattr(pipeline, "estimated", counted)
    callers = _callers_of_the_engine(monkeypatch)
    result = pipeline.calibrate(_spiked_and_trimmed(rec) if targetless else rec,
                                CalibConfig(targetless=targetless, force=True, clouds=False, geometry=False,
                                            compare_targetless=False))
    assert ways == ["PlaneWay" if targetless else "MarkerWay"], ways
    assert result.method == ("targetless" if targetless else "markers")
    assert "pipeline/loop.py" in callers and set(callers) <= ASKERS, sorted(set(callers))
    if targetless:
        notes = list(result.notes)
        assert notes[:1] == list(PlaneWay.NOTES), notes
        spike = next(i for i, s in enumerate(notes) if "jump away from their neighbours dropped" in s)
        trimmed = next(i for i, s in enumerate(notes) if "outside the joint states' time span trimmed" in s)
        assert (spike, trimmed) == (1, 2), notes


def test_the_loop_names_no_way() -> None:
    """Nothing of one way in the loop (no name of it in its code); the way is chosen in one place
    (lrfcal.pipeline._calibrate)."""
    tree = ast.parse(inspect.getsource(loop))
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    names |= {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    for p in [*_imports(Path(loop.__file__))]:
        names.add(p[1])
    for specific in ("MarkerWay", "PlaneWay", "MarkerEvidence", "PlaneEvidence", "lrfcal.stages.markers",
                     "lrfcal.stages.scene", "proposal_ahead"):
        assert specific not in names, specific
    assert inspect.getsource(pipeline._calibrate).count("PlaneWay") == 1, "the way is chosen in one place"


def test_each_way_reports_its_stages() -> None:
    assert MarkerWay.STAGES == MARKER_STAGES and "association" in MarkerWay.STAGES
    assert PlaneWay.STAGES == PLANE_STAGES and "planes" in PlaneWay.STAGES


@pytest.mark.parametrize("way", [MarkerWay, PlaneWay])
def test_a_way_keeps_no_state_between_its_steps(way: type) -> None:
    """A step passes what a later one needs as its result: no method but ``__init__`` assigns an attribute of the
    way (``self.x = ...``, also as a ``with ... as self.x`` target)."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(way)))
    set_in = []
    for fn in ast.walk(tree):
        if isinstance(fn, ast.FunctionDef) and fn.name != "__init__":
            for node in ast.walk(fn):
                if (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
                        and isinstance(node.value, ast.Name) and node.value.id == "self"):
                    set_in.append(f"{fn.name}: self.{node.attr}")
    assert not set_in, set_in


def test_the_way_protocol_types_its_steps() -> None:
    """The Way protocol is generic over what a way observes, its starts and its sets: no step takes or returns Any
    (mypy checks each way against it, tests/static_types.py)."""
    assert "Any" not in inspect.getsource(loop.Way).split('"""')[-1], "a step of Way is typed Any"
    assert len(loop.Way.__parameters__) == 3


def _lines_outside(rooms: tuple[str, ...], needle: Callable[[str], bool]) -> list[str]:
    return [f"{p.relative_to(ROOT)}:{i}" for p in sorted(SRC.rglob("*.py"))
            if p.relative_to(SRC).parts[0] not in rooms
            for i, line in enumerate(p.read_text().splitlines(), 1) if needle(line.split("#")[0])]


def test_the_covariance_is_widened_in_one_place() -> None:
    """No solution's covariance is replaced outside lrfcal/estimate (its widening: lrfcal.estimate.systematics)."""
    bad = _lines_outside(("estimate",), lambda line: "covariance=" in line and "sigma=" in line)
    assert not bad, bad


def test_the_servo_sign_and_the_dh_block_each_have_one_place() -> None:
    """The servo's sign is applied by JointStates.signed alone; the DH block of a solution is read by name
    (Solution.dh_sigma, params.dh), never sliced raw outside the model and the estimate."""
    negated = _lines_outside(("types",), lambda line: "positions_rad=-" in line.replace(" ", ""))
    raw = _lines_outside(("model", "estimate"), lambda line: "[6:10]" in line or "[6:]" in line)
    assert not negated and not raw, (negated, raw)


def test_refusals_are_told_apart_by_their_type(recording_of: Callable[[Any], Path]) -> None:
    """No refusal is recognised by its words (``... in str(err)``) in the method (the orchestrator, the stages, the
    estimate); a clock-offset start the recording refutes is a ClockStartError (a ClockOffsetError), which gets no
    hint about the clock offset (it names it itself)."""
    method = ("pipeline", "stages", "estimate")
    bad = [where for where in _lines_outside((), lambda line: "in str(" in line or ".startswith(CLOCK" in line)
           if Path(where).parts[2] in method]
    assert not bad, bad
    data = yaml.safe_load((SCENARIOS / "plane_30deg.yaml").read_text())
    rec = read_recording(recording_of(parse_scenario(with_changes(data, QUICK), "plane_30deg")))
    with pytest.raises(ClockStartError) as refused:
        pipeline.calibrate(rec, CalibConfig(clock_offset_s=0.9, clouds=False, geometry=False))  # beyond its bound
    assert isinstance(refused.value, ClockOffsetError) and isinstance(refused.value, CalibrationError)
    assert "note: the calibration started from" not in str(refused.value)
