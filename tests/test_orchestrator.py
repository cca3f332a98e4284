"""The method in one place (issue 45, item 3): lrfcal.pipeline._calibrate runs the same steps for both ways, and
each way is a class with those steps (lrfcal.stages.markers.MarkerWay, lrfcal.stages.scene.PlaneWay). Behaviour
(the same calibration.yaml as before) is held by the calibration tests and benchmarks/before_after.py."""

from __future__ import annotations

import ast
import inspect
import textwrap

import pytest

from lrfcal import pipeline
from lrfcal.stages.markers import STAGES as MARKER_STAGES
from lrfcal.stages.markers import MarkerWay
from lrfcal.stages.scene import PlaneWay
from lrfcal.stages.targetless import STAGES as PLANE_STAGES

STEPS = ("ahead", "observe", "starts", "refine", "checks")


def _calibrate_tree() -> ast.FunctionDef:
    source = textwrap.dedent(inspect.getsource(pipeline._calibrate))
    node = ast.parse(source).body[0]
    assert isinstance(node, ast.FunctionDef)
    return node


def test_the_orchestrator_is_short_and_runs_every_step_once() -> None:
    node = _calibrate_tree()
    lines = node.end_lineno - node.lineno + 1 if node.end_lineno else 0
    assert lines <= 45, f"pipeline._calibrate is {lines} lines, the orchestrator should read in about 40"
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
