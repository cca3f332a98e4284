"""The replicas of the real URG-04LX tilt stand (issue 54, scenarios/urg_box_60.yaml and urg_room_90.yaml): each
simulates as a step-and-scan recording the calibration reads as one (one angle per scan, ``servo.motion: step``), and
`lrfcal calibrate --targetless` (the installed console script) recovers the truth: every DH parameter it estimates
within 4 sigma of the true one. Short versions (coarse steps, a few dozen scans) keep the suite fast;
benchmarks/bench_replicas.py measures the full replicas over 40 seeds."""

from __future__ import annotations

import math
import subprocess
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import console_script

from lrfcal.io.recording import read_recording
from lrfsim.scenario.file import load_scenario, parse_scenario, with_changes
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import simulate

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
#: the short versions: steps of 1.5 deg (20 of the stand's 0.075 deg; a 60 deg pass in 41 scans, 90 deg in 61), one pass
SHORT: dict[str, Any] = {"servo.step_rad": math.radians(1.5), "servo.speed_rad_s": 5.0, "servo.passes": 1,
                         "servo.settle_s": 0.1}
DH = ("a", "alpha", "b", "beta")




def _short(name: str) -> dict[str, Any]:
    return with_changes(yaml.safe_load((SCENARIOS / f"{name}.yaml").read_text()), SHORT)


@pytest.mark.parametrize("name", ["urg_box_60", "urg_room_90"])
def test_the_shipped_replica_is_valid(name: str) -> None:
    """The full replica loads (step and scan, one scan per step, the step's move between two scans)."""
    sc = load_scenario(SCENARIOS / f"{name}.yaml")
    assert sc.servo.mode == "step" and sc.markers is None
    assert sc.servo.step_period_s == sc.sensor.scan_period_s
    assert math.isclose(sc.servo.step_rad, math.radians(0.075))


@pytest.mark.parametrize("name", ["urg_box_60", "urg_room_90"])
def test_replica_calibrates_targetless(name: str, tmp_path: Path) -> None:
    sc = parse_scenario(_short(name), name)
    result = simulate(sc)
    rec = write_recording(result, sc, tmp_path / "rec")
    # read as the real stand's recording is: one angle per scan, the scan's, taken at its stamp
    nominal = yaml.safe_load((rec / "nominal.yaml").read_text())
    assert nominal["servo"]["motion"] == "step" and "distances.csv" not in {p.name for p in rec.iterdir()}
    # the URG-04LX's range error along the scan declared, as its user's rig file would: estimated with the DH
    assert nominal["range_pattern"] is True
    recording = read_recording(rec, require_distances=False)
    assert recording.scans.angle_per_scan
    assert recording.joints.stamps_s.size == recording.scans.stamps_s.size == result.ranges_m.shape[0]
    np.testing.assert_allclose(np.diff(recording.joints.positions_rad[1:-1]), math.radians(1.5), atol=1e-12)
    if name == "urg_room_90":  # the stand is seen at large tilts only
        near = np.isfinite(result.ranges_m) & (result.ranges_m < 0.2)
        tilt = result.beam_lambda_rad[:, 0]
        assert near[tilt > math.radians(60)].any() and not near[tilt < math.radians(30)].any()

    # as a user runs it (no --force): both short replicas calibrate, the room with its stand declared and left out
    # (self_boxes) and the range pattern estimated; what the scene does not determine is held and named (here a, and
    # on the box b)
    proc = subprocess.run([console_script("lrfcal"), "calibrate", str(rec), "--targetless", "--no-figures", "-o",
                           str(tmp_path / "cal"), "-q"], capture_output=True, text=True, timeout=600)
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 0, proc.stderr
    cal = yaml.safe_load((tmp_path / "cal" / "calibration.yaml").read_text())
    assert cal["rig"]["range_pattern"] is True and cal["config"]["range_pattern"] is True
    truth = yaml.safe_load((rec / "ground_truth.yaml").read_text())["dh"]
    estimated = 0
    for p in DH:
        value, sigma = _value_and_sigma(cal, p)
        if sigma is None:  # held at the nominal value and named
            continue
        estimated += 1
        err = value - truth[p]
        if p in ("alpha", "beta"):
            err = math.remainder(err, 2 * math.pi)
        assert abs(err) <= 4 * sigma, f"{p}: error {err:.3g}, sigma {sigma:.3g}"
    assert estimated >= 1


def _value_and_sigma(cal: dict[str, Any], p: str) -> tuple[float, float | None]:
    """A DH parameter's value and 1-sigma in calibration.yaml (SI units; sigma None when held, as held_at_nominal
    names it)."""
    entry = cal["dh"][p]
    sigma = entry.get("sigma")
    held = p in (cal.get("held_at_nominal") or []) or sigma is None or not math.isfinite(float(sigma))
    return float(entry["value"]), None if held else float(sigma)


def test_the_mixed_pixels_the_simulator_makes_are_the_returns_beside_jump_edges(tmp_path: Path) -> None:
    """The returns the targetless calibration leaves out as beside a jump edge (lrfcal.stages.targetless.mixed_pixels)
    hold the mixed pixels of the short room replica: noise off, its footprint of 7 sub-rays against the centre ray
    alone, every return whose range the footprint moves by more than 1 cm (a range on neither surface) is among
    them, and they are a few per cent of the returns."""
    from lrfcal.stages.targetless import mixed_pixels

    ranges, rec = {}, None
    for rays in (7, 1):
        sc = parse_scenario(with_changes(_short("urg_room_90"), {"sensor.noise": False,
                                                                 "sensor.footprint_rays": rays}), "urg_room_90")
        folder = tmp_path / f"rays{rays}"
        write_recording(simulate(sc), sc, folder)
        got = read_recording(folder, require_distances=False)
        ranges[rays] = got.scans.ranges_m
        rec = rec or got
    assert rec is not None
    with np.errstate(invalid="ignore"):
        moved = np.abs(ranges[7] - ranges[1]) > 0.01  # NaN (no return in either) compares False
    flagged = mixed_pixels(rec.scans, rec.joints, 0.0, 0.0055)
    assert moved.sum() > 20  # the scene has edges the footprint straddles
    assert (moved & flagged).sum() >= 0.9 * moved.sum(), (int((moved & ~flagged).sum()), int(moved.sum()))
    assert flagged.mean() < 0.05


def test_the_stand_declared_in_the_rig_file_is_left_out(tmp_path: Path) -> None:
    """lrfsim declares the room replica's stand in nominal.yaml (``self_boxes``, boxes in M); the targetless
    calibration leaves the returns of the beams that meet them out (lrfcal.stages.targetless.own_returns): the
    stand's close returns, seen at large tilts only, and no return of the room itself; judged by the ray, so the
    ranges' noise does not choose which returns stay (the same returns with other ranges: the same choice)."""
    from lrfcal.stages.targetless import own_returns

    sc = parse_scenario(_short("urg_room_90"), "urg_room_90")
    result = simulate(sc)
    rec = write_recording(result, sc, tmp_path / "rec")
    assert len(yaml.safe_load((rec / "nominal.yaml").read_text())["self_boxes"]) == len(sc.rig.stand)
    got = read_recording(rec, require_distances=False)
    own = own_returns(got.scans, got.joints, 0.0, got.nominal.dh, got.nominal.self_boxes)
    tilt = result.beam_lambda_rad[:, 0]
    assert own[tilt > math.radians(60)].any() and not own[tilt < math.radians(30)].any()
    # the stand's parts and what their beams meet right behind them (the boxes' 2 cm margin): close returns only,
    # most of those within 20 cm (the rest: the desk top, 12 cm below the axis)
    with np.errstate(invalid="ignore"):
        near = got.scans.ranges_m < 0.2
    assert own.sum() > 1000 and np.all(got.scans.ranges_m[own] < 0.3)
    assert own[near].mean() > 0.6
    noisy = replace(got.scans, ranges_m=got.scans.ranges_m + np.random.default_rng(0).normal(0.0, 0.01,
                                                                                               got.scans.ranges_m.shape))
    assert np.array_equal(own_returns(noisy, got.joints, 0.0, got.nominal.dh, got.nominal.self_boxes), own)
