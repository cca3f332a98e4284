"""The method in one place (issue 45, item 3): lrfcal.pipeline._calibrate runs the same steps for both ways, and
each way is a class with those steps (lrfcal.stages.markers.MarkerWay, lrfcal.stages.scene.PlaneWay). Behaviour
(the same calibration.yaml as before) is held by the calibration tests and benchmarks/before_after.py."""

from __future__ import annotations

import ast
import inspect
import textwrap
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
import yaml

from lrfcal import pipeline
from lrfcal.config import CalibConfig
from lrfcal.io.recording import read_recording
from lrfcal.stages.markers import STAGES as MARKER_STAGES
from lrfcal.stages.markers import MarkerWay
from lrfcal.stages.scene import PlaneWay
from lrfcal.stages.targetless import STAGES as PLANE_STAGES
from lrfcal.types import JointStates
from lrfsim.scenario.file import parse_scenario, with_changes

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"

STEPS = ("ahead", "observe", "starts", "refine", "checks")


def _calibrate_tree() -> ast.FunctionDef:
    source = textwrap.dedent(inspect.getsource(pipeline._calibrate))
    node = ast.parse(source).body[0]
    assert isinstance(node, ast.FunctionDef)
    return node


def test_the_orchestrator_runs_every_step_once() -> None:
    node = _calibrate_tree()
    calls = [c.func.attr for c in ast.walk(node) if isinstance(c, ast.Call) and isinstance(c.func, ast.Attribute)
             and isinstance(c.func.value, ast.Name) and c.func.value.id == "way"]
    assert sorted(calls) == sorted(STEPS), calls


def test_the_orchestrator_names_no_way_specific_step() -> None:
    """Nothing of one way only in the orchestrator: the way is chosen once, the rest is the same for both."""
    names = {n.id for n in ast.walk(_calibrate_tree()) if isinstance(n, ast.Name)}
    names |= {n.attr for n in ast.walk(_calibrate_tree()) if isinstance(n, ast.Attribute)}
    for specific in ("fit_markers", "fit_scene", "PlaneEvidence", "MarkerEvidence", "starts_check",
                     "proposal_ahead", "targetless"):
        assert specific not in names, specific
    source = inspect.getsource(pipeline._calibrate)
    assert source.count("PlaneWay") == 1, "the way is chosen in one place"


@pytest.mark.parametrize("way", [MarkerWay, PlaneWay])
def test_each_way_has_the_steps(way: type) -> None:
    protocol = {name: list(inspect.signature(getattr(pipeline.Way, name)).parameters) for name in STEPS}
    for name, params in protocol.items():
        assert callable(getattr(way, name, None)), f"{way.__name__} has no step {name}"
        got = list(inspect.signature(getattr(way, name)).parameters)
        assert len(got) == len(params), f"{way.__name__}.{name}{got}: the protocol's takes {params}"


def test_each_way_reports_its_stages() -> None:
    assert MarkerWay.STAGES == MARKER_STAGES and "association" in MarkerWay.STAGES
    assert PlaneWay.STAGES == PLANE_STAGES and "planes" in PlaneWay.STAGES


@pytest.mark.parametrize("way", [MarkerWay, PlaneWay])
def test_a_way_keeps_no_state_between_its_steps(way: type) -> None:
    """A step passes what a later one needs as its result (the next step's argument): no method but ``__init__``
    assigns an attribute of the way (``self.x = ...``, also as a ``with ... as self.x`` target)."""
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
    """The Way protocol is generic over what each step returns: no step takes or returns Any."""
    source = inspect.getsource(pipeline.Way)
    assert "Any" not in source.split('"""')[-1], "a step of Way is typed Any"
    assert len(pipeline.Way.__parameters__) == 4


def test_notes_keep_their_order_way_first_then_the_scans_then_the_steps(
        recording_of: Callable[[Any], Path]) -> None:
    """The notes are returned by the stages and collected in the order they were appended before (issue 45): the
    plane way's own note first, then the orchestrator's on the scans (a spike dropped, scans beyond the joint states
    trimmed), then the way's steps'. (room_box in one quick pass, as tests/test_targetless.py's CLI test.)"""
    data = yaml.safe_load((SCENARIOS / "room_box.yaml").read_text())
    quick = {"servo.speed_rad_s": 1.0, "servo.passes": 1, "servo.settle_s": 0.05}
    rec = read_recording(recording_of(parse_scenario(with_changes(data, quick), "room_box")), require_distances=False)
    n = rec.joints.stamps_s.size
    positions = rec.joints.positions_rad.copy()
    positions[n // 3] += 0.5  # one encoder spike
    keep = slice(0, int(0.9 * n))  # the last tenth of the joint states missing: the scans beyond them trimmed
    rec = replace(rec, joints=JointStates(stamps_s=rec.joints.stamps_s[keep], positions_rad=positions[keep],
                                          name=rec.joints.name))
    result = pipeline.calibrate(rec, CalibConfig(targetless=True, force=True, clouds=False, geometry=False))
    notes = list(result.notes)
    assert notes[:1] == list(PlaneWay.NOTES), notes
    spike = next(i for i, s in enumerate(notes) if "jump away from their neighbours dropped" in s)
    trimmed = next(i for i, s in enumerate(notes) if "outside the joint states' time span trimmed" in s)
    assert (spike, trimmed) == (1, 2), notes
