"""Every fault of ``lrfsim.simulation.faults`` and every crash or bad input of issue 21, through the programs' entry
points as the console scripts call them (``main(argv)`` in this process: tests/test_cli_usage.py's ``_call``; the
installed scripts themselves run in tests/test_cli_usage.py, test_check.py, test_recording_faults.py and others).

A recording with faults (simulated once per test run) is calibrated by ``lrfcal calibrate`` as a user would:
the exit code is the documented one (0 calibrated, 2 bad input, 3 refused), a refusal or a bad input is exactly one
``error:`` line on stderr, no traceback ever, and the output folder is either complete (every file the report
links) or absent. The recordings are a short plane_30deg sweep (about 370 scans) so that the four of them and
their calibrations cost about a minute of one core.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from pathlib import Path

import pytest
import yaml
from test_cli_usage import ROOT, _call, _one_error_line

from lrfsim.scenario.file import Scenario, parse_scenario

SCENARIO = ROOT / "scenarios" / "plane_30deg.yaml"

#: the faults, grouped so that each recording calibrates (combo, timing) or is refused for one named reason
FAULTS: dict[str, dict[str, object]] = {
    # every fault that the calibration repairs or leaves out, at once
    "combo": {"faults": {"tape_outliers": [{"pair": ["m00", "m12"], "error_m": 0.3}], "false_blobs": 3,
                         "occluded_markers": 1, "dropped_scans_fraction": 0.05, "encoder_spikes": 3}},
    # an untold 100 ms clock offset (scans trimmed at the ends) and scan stamps taken at receive time
    "timing": {"faults": {"stamp_latency_s": 0.005, "stamp_jitter_s": 0.01}, "servo": {"clock_offset_s": 0.1}},
    "inverted": {"faults": {"inverted_servo": True}},
    "noisy": {"faults": {"range_noise_scale": 3.0}},
}

#: what ground_truth.yaml records under ``faults`` for each recording
RECORDED = {"combo": {"tape_outliers", "false_blobs", "occluded_markers", "dropped_scans", "encoder_spikes"},
            "timing": {"receive_stamps"}, "inverted": {"inverted_servo"}, "noisy": {"range_noise_scale"}}


def _scenario_data(name: str, changes: dict[str, object]) -> dict[str, object]:
    data = copy.deepcopy(yaml.safe_load(SCENARIO.read_text()))
    data["name"] = name
    data["servo"]["speed_rad_s"] = 0.785  # 45 deg/s: 2 passes of +-90 deg in about 370 scans
    for section, values in changes.items():
        data.setdefault(section, {}).update(values)  # type: ignore[union-attr]
    return data


def _scenario(tmp: Path, name: str, changes: dict[str, object]) -> Path:
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(_scenario_data(name, changes), sort_keys=False))
    return path


@pytest.fixture(scope="session")
def recordings(recording_of: Callable[[Scenario], Path]) -> dict[str, Path]:
    """The four faulty recordings, simulated once per test run (tests/conftest.py) and only read here."""
    out = {}
    for name, changes in FAULTS.items():
        rec = recording_of(parse_scenario(_scenario_data(name, changes), f"{name}.yaml"))
        injected = yaml.safe_load((rec / "ground_truth.yaml").read_text())["faults"]
        assert set(injected) == RECORDED[name], injected  # ground_truth.yaml says what was done
        out[name] = rec
    return out


def _calibrated(proc, out: Path) -> str:
    """Assert a calibration that exited 0, printed no traceback and wrote a complete folder; return report.md."""
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 0, proc.stderr
    report = (out / "report.md").read_text()
    for name in ("calibration.yaml", "rig.urdf", "cloud_before.ply", "cloud_after.ply"):
        assert (out / name).is_file(), name
    linked = re.findall(r"!\[\w+\]\(([\w.]+\.png)\)", report)
    assert sorted(linked) == ["alignment.png", "intensity.png", "residuals.png"], linked
    assert all((out / f).stat().st_size > 10_000 for f in linked)
    assert "could not be drawn" not in report
    return report


def _refused(proc, out: Path) -> str:
    line = _one_error_line(proc, code=3)
    assert not out.exists() and not list(out.parent.glob(f".{out.name}*")), "a refusal writes nothing"
    return line


def test_repaired_faults_calibrate_with_figures(recordings: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "cal"
    report = _calibrated(_call("lrfcal", "calibrate", recordings["combo"], "-o", out, "--no-baseline"),
                         out)
    assert "tape pair m00-m12 dropped" in report  # the misread tape pair is named
    assert "joint-state samples that jump away from their neighbours dropped" in report


def test_untold_clock_offset_and_receive_stamps_calibrate_with_figures(recordings: dict[str, Path],
                                                                      tmp_path: Path) -> None:
    """The crash of issue 21: the scans the joint states do not cover are trimmed, and the figures still match."""
    out = tmp_path / "cal"
    report = _calibrated(_call("lrfcal", "calibrate", recordings["timing"], "-o", out, "--no-baseline"),
                         out)
    assert "scans outside the joint states' time span trimmed" in report
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    tau, sigma = cal["clock_offset_s"]["value"], cal["clock_offset_s"]["sigma"]
    # 100 ms offset + 5 ms latency + 5 ms mean jitter
    assert abs(tau - 0.110) < max(4 * sigma, 0.002), (tau, sigma)


def test_wrong_clock_offset_option_is_refused_naming_it(recordings: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "cal"
    line = _refused(_call("lrfcal", "calibrate", recordings["timing"], "-o", out, "--clock-offset", "5",
                         "--no-baseline"), out)
    assert "clock offset" in line and "--clock-offset +5 s" in line


def test_inverted_servo_is_refused_naming_the_sign(recordings: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "cal"
    line = _refused(_call("lrfcal", "calibrate", recordings["inverted"], "-o", out, "--no-baseline"), out)
    assert "servo.sign: -1" in line


def test_three_times_the_noise_is_refused_naming_range_sigma(recordings: dict[str, Path], tmp_path: Path) -> None:
    out = tmp_path / "cal"
    line = _refused(_call("lrfcal", "calibrate", recordings["noisy"], "-o", out, "--no-baseline"), out)
    assert "reduced chi-square" in line and "--range-sigma" in line


@pytest.mark.parametrize(("key", "value", "words"), [
    ("dh.a", 10, ["dh.a", "millimetres", "0.01 m"]),
    ("dh.b", -15, ["dh.b", "millimetres"]),
    ("mount.z", 980, ["mount.z", "millimetres", "0.98 m"]),
    ("marker_radius_m", 5, ["marker_radius_m", "millimetres", "0.005 m"]),
    ("dh.alpha", 90, ["dh.alpha", "degrees"]),
])
def test_unit_mistakes_in_the_rig_file_name_field_and_unit(recordings: dict[str, Path], tmp_path: Path, key: str,
                                                           value: float, words: list[str]) -> None:
    rig = yaml.safe_load((recordings["combo"] / "nominal.yaml").read_text())
    node = rig
    *head, last = key.split(".")
    for k in head:
        node = node[k]
    node[last] = value
    bad = tmp_path / "nominal.yaml"
    bad.write_text(yaml.safe_dump(rig))
    out = tmp_path / "cal"
    line = _one_error_line(_call("lrfcal", "calibrate", recordings["combo"], "-o", out, "--nominal", bad))
    assert all(w in line for w in words), line
    assert not out.exists()


@pytest.mark.parametrize(("section", "field", "value", "named"), [
    ("sensor", "noise_bands", [{"up_to_m": 10.0, "sigma_m": 1e9}], "sensor.noise_bands[0].sigma_m"),
    ("sensor", "range_max_m", 0.01, "range_max_m"),  # below range_min_m
    ("sensor", "time_increment_s", 0.01, "time_increment_s"),  # 1081 beams would take 10.8 s of a 25 ms scan
    ("servo", "settle_s", 1e7, "servo.settle_s"),
    ("tape", "sigma_m", 5.0, "tape.sigma_m"),
])
def test_absurd_scenario_values_are_refused_naming_the_field(tmp_path: Path, section: str, field: str,
                                                             value: object, named: str) -> None:
    path = _scenario(tmp_path, "absurd", {section: {field: value}})
    out = tmp_path / "rec"
    line = _one_error_line(_call("lrfsim", "simulate", path, "-o", out))
    assert named in line and "absurd.yaml" in line, line
    assert not out.exists()


def test_unwritable_output_is_found_before_the_work(recordings: dict[str, Path]) -> None:
    proc = _call("lrfcal", "calibrate", recordings["combo"], "-o", "/proc/lrf_out")
    line = _one_error_line(proc)
    assert "/proc/lrf_out" in line and "cannot write" in line
    assert ".figures-" not in line and ".tmp" not in line  # never the tool's own temporary paths


def test_garbage_mesh_is_named_as_unreadable(tmp_path: Path) -> None:
    junk = tmp_path / "junk.stl"
    junk.write_bytes(bytes(range(256)) * 12)  # neither a binary nor an ASCII STL
    path = _scenario(tmp_path, "mesh", {"scene": {"meshes": [{"file": str(junk)}]}})
    line = _one_error_line(_call("lrfsim", "simulate", path, "-o", tmp_path / "rec"))
    assert "junk.stl" in line and "not a mesh trimesh can read" in line and "charset" not in line


def test_version() -> None:
    for prog in ("lrfcal", "lrfsim"):
        proc = _call(prog, "--version")
        assert proc.returncode == 0 and re.fullmatch(rf"{prog} \d+\.\d+\.\d+\S*\n", proc.stdout), proc.stdout


def test_force_writes_a_refused_result_with_its_failed_checks_and_no_figures(recordings: dict[str, Path],
                                                                             tmp_path: Path) -> None:
    out = tmp_path / "cal"
    proc = _call("lrfcal", "calibrate", recordings["noisy"], "-o", out, "--no-baseline", "--force", "--no-figures")
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    report = (out / "report.md").read_text()
    assert "| reduced chi-square | **FAILED** |" in report
    assert "not drawn (--no-figures)" in report and not list(out.glob("*.png"))
    checks = yaml.safe_load((out / "calibration.yaml").read_text())["checks"]
    assert any(c["name"] == "reduced chi-square" and not c["passed"] for c in checks), checks
