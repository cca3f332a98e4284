"""The result typed by its evidence (lrfcal.result): a marker result and a targetless one, the same solution, written
by each reader as its evidence says (calibration.yaml, report.md, the terminal summary, the figures' choice, the truth
frame, lrfsim's comparison), with no optional field to test."""

from __future__ import annotations

import dataclasses
import io
import math
from pathlib import Path

import numpy as np
import pytest
from synthetic import make_result, marker_positions_W

import lrfcal
from lrfcal.io.calibration_yaml import calibration_dict
from lrfcal.io.truth import truth_frame
from lrfcal.report.figures import needs_clouds
from lrfcal.report.markdown import render_report, residual_summary
from lrfcal.result import CalibrationResult, MarkerEvidence, PlaneEvidence, PlaneFit
from lrfcal.types import ScenePlane, SurfaceReturns


@pytest.fixture(scope="module")
def marked() -> CalibrationResult:
    return make_result(n_scans=40, n_beams=121)


def _plane_evidence(n_returns: int = 30) -> PlaneEvidence:
    """Two planes of a scene, b held at nominal, and n_returns plane returns on them."""
    normals = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    planes = tuple(ScenePlane(n, 2.0 + k, 100, 0.002, np.zeros(3)) for k, n in enumerate(normals))
    fit = PlaneFit(planes, np.array([0.004, 0.005]), np.array([0.002, 0.003]), np.array([100, 120]), ("b",),
                   "the scene does not determine b", 3, normals, normals)
    k = np.arange(n_returns)
    returns = SurfaceReturns(k, k, np.zeros(n_returns), np.zeros(n_returns), np.full(n_returns, 2.0), k % 2,
                             normals[k % 2], np.full(n_returns, 2.0))
    return PlaneEvidence(plane_fit=fit, returns=returns)


@pytest.fixture(scope="module")
def targetless(marked: CalibrationResult) -> CalibrationResult:
    """The same recording and solution with plane evidence instead of the markers."""
    return dataclasses.replace(marked, evidence=_plane_evidence())


def test_the_evidence_names_the_method_and_is_public(marked: CalibrationResult, targetless: CalibrationResult) -> None:
    assert isinstance(marked.evidence, MarkerEvidence) and marked.method == "markers"
    assert isinstance(targetless.evidence, PlaneEvidence) and targetless.method == "targetless"
    assert (lrfcal.MarkerEvidence, lrfcal.PlaneEvidence, lrfcal.PlaneFit) == (MarkerEvidence, PlaneEvidence, PlaneFit)
    assert {"MarkerEvidence", "PlaneEvidence", "PlaneFit"} <= set(lrfcal.__all__)
    with pytest.raises(dataclasses.FrozenInstanceError):
        marked.evidence.baseline = marked.solution  # type: ignore[misc]
    # the marker evidence's counts: the returns on each marker of the map
    counts = marked.evidence.marker_counts()
    obs = marked.evidence.observations
    assert counts.sum() == np.count_nonzero(obs.marker >= 0) and counts.size == len(marked.evidence.markers.marker_ids)


def test_calibration_yaml_keys_follow_the_evidence(marked: CalibrationResult, targetless: CalibrationResult) -> None:
    m, t = calibration_dict(marked), calibration_dict(targetless)
    assert m["method"] == "markers" and {"markers", "marker_map", "association", "surfaces"} <= set(m)
    assert m["mount"] is not None and "held_at_nominal" not in m and "planes" not in m
    assert t["method"] == "targetless" and t["mount"] is None and t["mount_rotation_sigma_rad"] is None
    assert t["held_at_nominal"] == ["b"] and [p["n_returns"] for p in t["planes"]] == [100, 120]
    assert not {"markers", "marker_map", "association", "surfaces"} & set(t) and t["baseline"] is None
    # what both have is written the same: the solution's DH
    assert m["dh"] == t["dh"]
    # the paper's baseline is the marker evidence's
    with_paper = dataclasses.replace(marked, evidence=dataclasses.replace(marked.evidence, baseline=marked.solution))
    assert calibration_dict(with_paper)["baseline"]["dh"] == m["dh"]


def test_report_summary_and_figures_follow_the_evidence(marked: CalibrationResult,
                                                       targetless: CalibrationResult) -> None:
    from rich.console import Console

    from lrfcal.report.summary import print_summary

    md_m, md_t = render_report(marked), render_report(targetless)
    assert "## Per-marker residuals" in md_m and "## The scene's planes" not in md_m and "(targetless" not in md_m
    assert "## The scene's planes" in md_t and "## Per-marker residuals" not in md_t
    assert md_t.startswith("# Rotating LRF calibration (targetless") and "| b | mm |" in md_t
    b_row = next(line for line in md_t.splitlines() if line.startswith("| b |"))
    assert "(held)" in b_row and not any(line.startswith("| x |") for line in md_t.splitlines())
    assert "marker returns on" in residual_summary(marked)
    assert residual_summary(targetless).endswith("on 2 planes of the scene (targetless)")
    assert not needs_clouds(marked) and needs_clouds(targetless)
    for result, mount_shown in ((marked, True), (targetless, False)):
        console = Console(file=io.StringIO(), width=200)
        print_summary(result, console)
        text = console.file.getvalue()  # type: ignore[attr-defined]
        assert ("x (mm)" in text) is mount_shown and ("targetless:" in text) is not mount_shown


def test_truth_frame_and_comparison_follow_the_evidence(marked: CalibrationResult,
                                                        targetless: CalibrationResult) -> None:
    """The marker frame W exists only with markers: the truth aligns to it there, and a targetless comparison has
    no mount errors (NaN) rather than a failure."""
    from lrfcal.model.kinematics import Pose
    from lrfsim.scenario.sections import Tolerances
    from lrfsim.trials.compare import Truth, compare

    ids = marked.evidence.markers.marker_ids
    truth = {"markers": dict(zip(ids, marker_positions_W().tolist(), strict=True))}
    found = truth_frame(marked, truth)
    assert found is not None and np.allclose(found[0], np.eye(4), atol=2e-3)  # the map: the truth and tape noise
    assert truth_frame(targetless, truth) is None
    params = targetless.solution.params
    true = Truth(params.dh, Pose(0, 0, 0, 0, 0, 0), {}, None, 0.0, None)
    c = compare(targetless, true, Tolerances())
    assert math.isnan(c.mount_position_error_m) and c.paper_mount_position_error_m is None
    assert all(abs(r.ours - r.truth) < 1e-12 for r in c.dh_rows)


def test_viewer_logs_what_the_evidence_holds(marked: CalibrationResult, targetless: CalibrationResult,
                                             tmp_path: Path) -> None:
    """The rerun recording of a targetless result: its clouds and the rig, nothing of markers (a marker result's
    entities are tests/test_viz.py's)."""
    pytest.importorskip("rerun")
    from test_viz import read_rrd

    from lrfcal.report import viz

    viz.log_calibration(targetless, rrd_path=tmp_path / "t.rrd")
    viz.log_calibration(marked, rrd_path=tmp_path / "m.rrd")
    t, m = read_rrd(tmp_path / "t.rrd"), read_rrd(tmp_path / "m.rrd")
    assert {"world/before/cloud", "world/after/cloud", "world/M"} <= set(t)
    assert not any(k.startswith(("world/markers", "intensity_image")) or k.endswith("returns") for k in t)
    assert {"world/markers/mds", "intensity_image", "world/after/returns"} <= set(m)
