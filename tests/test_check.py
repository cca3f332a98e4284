"""`lrfcal check` (issue 55): is a calibration still valid for a new recording of the same rig?

Through the INSTALLED console script: a simulated tunnel_v pair without drift (exit 0, check.yaml, report.md,
check.png, a history row appended, the calibration folder untouched) and with a 3 mm change of a (exit 4, naming a
first); a targetless pair (room_box); a real recording checked against its own calibration (valid, or not testable
with the reason); bad input in one line and exit 2 (through the command's entry point in this process, tests/
test_cli_usage.py's ``_call``) (not a calibration, another scanner, topics the calibration's rig
file does not find, a history inside the calibration folder). And the joint test's arithmetic
(lrfcal.estimate.drift). The false-alarm and detection rates are Monte-Carlo targets: benchmarks/bench_check.py,
docs/check.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import SCENARIOS, real_bag
from test_cli_usage import _call, _one_error_line, _run, _tree

from lrfsim.scenario.file import Scenario, load_scenario
from lrfsim.trials.variants import with_field


def test_the_joint_test_and_its_smallest_drift() -> None:
    from scipy.stats import chi2, ncx2

    from lrfcal.estimate.drift import chi2_threshold, detectable_drift, drift_test

    names = ["a", "b", "clock_offset"]
    Cs = np.array([[4e-8, 1e-8, 0.0], [1e-8, 1e-8, 0.0], [0.0, 0.0, 1e-7]])
    d = {"a": 9e-4, "b": 0.0, "clock_offset": 1e-4}
    t = drift_test(names, {n: 0.0 for n in names}, d, d, Cs, Cs, 0.05, {"mount": "not tested"})
    C = 2 * Cs
    v = np.array([d[n] for n in names])
    assert t.statistic == pytest.approx(float(v @ np.linalg.solve(C, v)))
    assert t.dof == 3 and t.threshold == pytest.approx(chi2.isf(0.05, 3)) == chi2_threshold(3, 0.05)
    assert t.drifted and t.named_first == "a"  # a explains most of the statistic
    assert [p.name for p in t.not_tested] == ["mount"] and not t.not_tested[0].tested
    assert t.parameters[0].z == pytest.approx(9e-4 / math.sqrt(8e-8))
    # the smallest drift detected with 95 %: the non-central chi-square at it exceeds the threshold with 95 %
    delta = detectable_drift(C, 0.05, 0.95)
    inv = np.linalg.inv(C)
    for i in range(3):
        assert ncx2.sf(t.threshold, 3, delta[i] ** 2 * inv[i, i]) == pytest.approx(0.95, abs=1e-6)
    nothing = drift_test(names, d, d, {n: 0.0 for n in names}, Cs, Cs, 0.05)
    assert not nothing.drifted and nothing.statistic == 0.0 and nothing.moved == ()


def _second(scenario: Scenario, seed: int, **truth: float) -> Scenario:
    """``scenario`` with another seed (another noise and laser phase) and its truth moved (dotted key -> change)."""
    out = scenario.model_copy(update={"seed": seed})
    for key, delta in truth.items():
        node = out.model_dump(mode="python")
        for k in key.split("__"):
            node = node[k]
        out = with_field(out, key.replace("__", "."), float(node) + delta)
    return out


@pytest.fixture(scope="module")
def tunnel(shipped_recording: Callable[[str], Path], recording_of: Callable[[Scenario], Path],
           tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """tunnel_v's recording calibrated by the installed `lrfcal calibrate`, a second recording of it (another seed)
    and one of the rig with a 3 mm larger a (the same other seed)."""
    scenario = load_scenario(SCENARIOS / "tunnel_v.yaml")
    first = shipped_recording("tunnel_v")
    cal = tmp_path_factory.mktemp("check") / "cal"
    proc = _run("lrfcal", "calibrate", first, "-o", cal, "--no-figures", "-q", timeout=300)
    assert proc.returncode == 0, proc.stderr
    return {"cal": cal, "same": recording_of(_second(scenario, 2)),
            "drifted": recording_of(_second(scenario, 2, rig__dh__a=0.003))}


def test_an_unchanged_rig_is_still_valid_and_a_drifted_one_named(tunnel: dict[str, Path], tmp_path: Path) -> None:
    before = _tree(tunnel["cal"])
    history = tmp_path / "history.csv"
    ok = _run("lrfcal", "check", tunnel["cal"], tunnel["same"], "-o", tmp_path / "ok", "--history", history,
              timeout=300)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("still valid: no change in a, alpha, b, beta, clock_offset"), ok.stdout
    assert "not tested: mount" in ok.stdout
    data = yaml.safe_load((tmp_path / "ok" / "check.yaml").read_text())
    assert data["verdict"] == "still valid" and data["test"]["false_alarm"] == 0.05
    assert data["test"]["dof"] == sum(p["tested"] for p in data["parameters"].values()) >= 5
    assert not data["parameters"]["mount"]["tested"] and "--fixed-mount" in data["parameters"]["mount"]["why"]
    for p in ("a", "alpha", "b", "beta", "clock_offset"):
        row = data["parameters"][p]
        assert row["tested"] and row["change"] == pytest.approx(row["new"] - row["saved"], abs=1e-12)
        assert row["z"] == pytest.approx(row["change"] / row["sigma"])
    assert {"check.png", "report.md"} <= {p.name for p in (tmp_path / "ok").iterdir()}
    assert "still valid" in (tmp_path / "ok" / "report.md").read_text()

    bad = _run("lrfcal", "check", tunnel["cal"] / "calibration.yaml", tunnel["drifted"], "-o", tmp_path / "bad",
               "--history", history, "--no-figures", timeout=300)
    assert bad.returncode == 4, bad.stderr
    assert bad.stdout.startswith("drifted: a +"), bad.stdout  # the 3 mm of a, named first
    data = yaml.safe_load((tmp_path / "bad" / "check.yaml").read_text())
    assert data["verdict"] == "drifted" and data["test"]["named"][0] == "a"
    assert data["parameters"]["a"]["change"] == pytest.approx(0.003, abs=5 * data["parameters"]["a"]["sigma"])
    rows = history.read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("time,calibration,recording,verdict")
    assert ",still valid," in rows[1] and ",drifted," in rows[2]
    assert _tree(tunnel["cal"]) == before  # the calibration (an input) is never written


def test_bad_input_is_one_line_and_exit_2(tunnel: dict[str, Path], tmp_path: Path) -> None:
    cal, rec = tunnel["cal"], tunnel["same"]
    # a file that is not a calibration
    line = _one_error_line(_call("lrfcal", "check", rec / "nominal.yaml", rec, "-o", tmp_path / "o1"))
    assert "not a calibration" in line and "nominal.yaml" in line
    # a calibration of another rig: another beam count, another scanner
    data = yaml.safe_load((cal / "calibration.yaml").read_text())
    for key, value in (("beams", 721), ("angle_increment_rad", math.radians(0.352))):
        other = tmp_path / f"other_{key}.yaml"
        other.write_text(yaml.safe_dump({**data, "scanner": {**data["scanner"], key: value}}))
        line = _one_error_line(_call("lrfcal", "check", other, rec, "-o", tmp_path / "o2"))
        assert "a calibration of another rig" in line and "scanner" in line
    # a recording whose topics the calibration's rig file does not find
    moved = tmp_path / "moved.yaml"
    moved.write_text(yaml.safe_dump({**data, "rig": {**data["rig"], "scan": {"topic": "/laser"}}}))
    line = _one_error_line(_call("lrfcal", "check", moved, rec, "-o", tmp_path / "o3"))
    assert "/laser" in line and "not in bag" in line and "--nominal" in line
    # outputs never inside an input: the history in the calibration folder, -o the calibration folder
    line = _one_error_line(_call("lrfcal", "check", cal, rec, "-o", tmp_path / "o4", "--history", cal / "h.csv"))
    assert "--history" in line and "calibration" in line
    _one_error_line(_call("lrfcal", "check", cal, rec, "-o", cal))
    line = _one_error_line(_call("lrfcal", "check", cal, rec, "-o", tmp_path / "o5", "--false-alarm", "0.7"))
    assert "--false-alarm" in line
    assert not any((tmp_path / f"o{i}").exists() for i in range(1, 6))


def test_a_targetless_pair(targetless_calibrated: Callable[[str], tuple[Path, Path, object]],
                           recording_of: Callable[[Scenario], Path], tmp_path: Path) -> None:
    _, cal, _ = targetless_calibrated("room_box")
    # the new recording one quick pass (a fifth of the scans): the check compares what both estimate (the clock
    # offset, estimated only from a sweep both ways, is then not tested)
    second = _second(load_scenario(SCENARIOS / "room_box.yaml"), 5)
    for key, value in (("servo.passes", 1), ("servo.speed_rad_s", 1.0), ("servo.settle_s", 0.05)):
        second = with_field(second, key, value)
    second = recording_of(second)
    proc = _run("lrfcal", "check", cal, second, "-o", tmp_path / "chk", "--no-figures", timeout=300)
    assert proc.returncode == 0, proc.stderr
    data = yaml.safe_load((tmp_path / "chk" / "check.yaml").read_text())
    assert data["method"] == {"saved": "targetless", "new": "targetless"}
    held = [n for n, p in data["parameters"].items() if not p["tested"]]
    assert "mount" not in data["parameters"]  # never estimated without markers: not even listed as untested
    assert all(data["parameters"][n]["why"] for n in held)
    assert data["test"]["dof"] >= 3


def test_a_real_recording_against_its_own_calibration(urg_from_the_authors_nominal: Callable[[str], object],
                                                      tmp_path: Path) -> None:
    """The URG-04LX stand's recording calibrated targetless from its authors' nominal (the session's, with --force: its
    calibration is refused today), written as `lrfcal calibrate --force` writes it, and checked against its own
    recording through the console script: still valid, or not testable (exit 3) with the reason."""
    from test_real_bags import URG_SCAN, URG_SERVO

    from lrfcal.io.calibration_yaml import calibration_dict

    bag = real_bag("cardboard_box")
    result = urg_from_the_authors_nominal("cardboard_box")
    data = calibration_dict(result)  # type: ignore[arg-type]
    data["rig"] = {**data["rig"], "scan": URG_SCAN.model_dump(mode="json", exclude_none=True),
                   "servo": URG_SERVO.model_dump(mode="json", exclude_none=True)}  # read from the bag as it was
    (tmp_path / "cal").mkdir()
    (tmp_path / "cal" / "calibration.yaml").write_text(yaml.safe_dump(data))
    chk = _run("lrfcal", "check", tmp_path / "cal", bag, "-o", tmp_path / "chk", "-q", timeout=600)
    if chk.returncode == 3:
        line = _one_error_line(chk, 3)
        assert line.startswith("error: check: "), line
        failed = [c["name"] for c in data["checks"] if not c["passed"]]
        assert all(n in line for n in failed), line  # the reason: the checks its calibration failed
    else:
        assert chk.returncode == 0, chk.stderr
        assert chk.stdout.startswith("still valid"), chk.stdout
