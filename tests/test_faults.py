"""Fault injection (lrfsim.simulation.faults): each fault, alone, changes the recording exactly as documented."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from lrfcal.errors import InputError
from lrfcal.stages.detection import detect
from lrfcal.types import Scans
from lrfsim.scenario.file import Scenario, parse_scenario
from lrfsim.simulation.faults import apply_faults, bright_mask, marker_returns, scale_range_noise
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import SimResult, simulate

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def _data(**faults: Any) -> dict[str, Any]:
    """tunnel_v, a quick +-0.5 rad sweep at 1 rad/s (63 scans, 8 markers seen), with ``faults``."""
    data = copy.deepcopy(yaml.safe_load((SCENARIOS / "tunnel_v.yaml").read_text()))
    data["servo"].update({"start_rad": 0.5, "end_rad": -0.5, "speed_rad_s": 1.0, "passes": 1, "settle_s": 0.05})
    data["faults"] = faults
    return data


def _scenario(**faults: Any) -> Scenario:
    return parse_scenario(_data(**faults), "test")


@pytest.fixture(scope="module")
def clean() -> SimResult:
    return simulate(_scenario())


def _scans(r: SimResult, scenario: Scenario) -> Scans:
    s = scenario.sensor
    return Scans(r.scan_stamps_s, r.ranges_m, r.intensities, r.mu_rad, s.time_increment_s, s.scan_period_s,
                 s.range_min_m, s.range_max_m)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.array_equal(a, b, equal_nan=True))


def test_no_faults_changes_nothing(clean: SimResult) -> None:
    out = apply_faults(clean, _scenario())
    assert out.faults == {} and clean.faults == {}
    assert _same(out.ranges_m, clean.ranges_m) and _same(out.intensities, clean.intensities)
    assert _same(out.joints.positions_rad, clean.joints.positions_rad)
    assert _same(out.tape.distances_m, clean.tape.distances_m)


@pytest.mark.parametrize("pair", [["m03", "m01"], 7])
def test_tape_outlier(clean: SimResult, pair: list[str] | int) -> None:
    out = apply_faults(clean, _scenario(tape_outliers=[{"pair": pair, "error_m": 0.5}]))
    diff = out.tape.distances_m - clean.tape.distances_m
    changed = np.nonzero(diff)[0]
    assert changed.size == 1 and math.isclose(diff[changed[0]], 0.5, abs_tol=1e-12)
    ids = clean.tape.marker_ids
    row = int(changed[0])
    if isinstance(pair, int):
        assert row == pair
    else:
        assert {ids[int(k)] for k in clean.tape.pairs[row]} == set(pair)
    (rec,) = out.faults["tape_outliers"]
    assert rec["row"] == row and rec["error_m"] == 0.5 and math.isclose(rec["measured_m"], out.tape.distances_m[row])
    assert _same(out.ranges_m, clean.ranges_m)  # nothing else


@pytest.mark.parametrize(("pair", "match"), [(["m03", "zz"], "unknown marker"), (9999, "beyond")])
def test_tape_outlier_bad_pair(clean: SimResult, pair: object, match: str) -> None:
    with pytest.raises(InputError, match=match):
        apply_faults(clean, _scenario(tape_outliers=[{"pair": pair, "error_m": 0.5}]))


def test_inverted_servo(clean: SimResult) -> None:
    out = apply_faults(clean, _scenario(inverted_servo=True))
    assert np.array_equal(out.joints.positions_rad, -clean.joints.positions_rad)
    assert np.array_equal(out.joints.velocities_rad_s, -clean.joints.velocities_rad_s)
    assert np.any(clean.joints.positions_rad != 0)
    assert np.array_equal(out.joints.true_positions_rad, clean.joints.true_positions_rad)  # truth unchanged
    assert np.array_equal(out.beam_lambda_rad, clean.beam_lambda_rad)
    assert out.faults == {"inverted_servo": True}


def test_occluded_markers(clean: SimResult) -> None:
    scenario = _scenario(occluded_markers=2)
    out = apply_faults(clean, scenario)
    rec = out.faults["occluded_markers"]
    ids = clean.truth.marker_ids
    before = marker_returns(clean, scenario)
    gone = [ids.index(m) for m in rec["markers"]]
    assert len(gone) == 2 and all(np.any(before == k) for k in gone)
    # exactly the covered markers' returns changed, and they are no longer bright
    cells = np.isin(before, gone)
    assert rec["n_cells"] == int(cells.sum()) > 0
    assert sorted(map(tuple, rec["cells"])) == sorted(map(tuple, np.argwhere(cells).tolist()))
    assert _same(out.ranges_m[~cells], clean.ranges_m[~cells])
    assert _same(out.intensities[~cells], clean.intensities[~cells])
    assert not bright_mask(out, scenario)[cells].any()
    after = marker_returns(out, scenario)
    assert not np.isin(after, gone).any()
    assert set(np.unique(after[after >= 0])) == set(np.unique(before[before >= 0])) - set(gone)
    # the surface behind: within a few cm of the marker returns' own ranges (markers sit 5 mm off the wall)
    r_old, r_new = clean.ranges_m[cells], out.ranges_m[cells]
    assert np.all(np.isfinite(r_new)) and np.all(np.abs(r_new - r_old) < 0.1)


def test_false_blobs(clean: SimResult) -> None:
    scenario = _scenario(false_blobs=3)
    out = apply_faults(clean, scenario)
    spots = out.faults["false_blobs"]
    assert len(spots) == 3
    cells = np.zeros(clean.ranges_m.shape, dtype=bool)
    for spot in spots:
        c = np.array(spot["cells"])
        assert 2 <= len(c) <= 12
        cells[c[:, 0], c[:, 1]] = True
    assert _same(out.ranges_m, clean.ranges_m)
    assert _same(out.intensities[~cells], clean.intensities[~cells])
    assert bright_mask(out, scenario)[cells].all() and not bright_mask(clean, scenario)[cells].any()
    assert not (marker_returns(out, scenario)[cells] >= 0).any()  # not on a marker
    n_clean, n_out = len(detect(_scans(clean, scenario)).blobs), len(detect(_scans(out, scenario)).blobs)
    assert n_out == n_clean + 3


def test_dropped_scans(clean: SimResult) -> None:
    out = apply_faults(clean, _scenario(dropped_scans_fraction=0.2))
    dropped = out.faults["dropped_scans"]
    S = clean.ranges_m.shape[0]
    assert len(dropped) == round(0.2 * S) and len(set(dropped)) == len(dropped)
    keep = np.setdiff1d(np.arange(S), dropped)
    assert out.ranges_m.shape == (S - len(dropped), clean.ranges_m.shape[1])
    assert _same(out.ranges_m, clean.ranges_m[keep]) and _same(out.intensities, clean.intensities[keep])
    assert np.array_equal(out.scan_stamps_s, clean.scan_stamps_s[keep])
    assert np.array_equal(out.beam_lambda_rad, clean.beam_lambda_rad[keep])
    assert np.array_equal(out.joints.positions_rad, clean.joints.positions_rad)


def test_encoder_spikes(clean: SimResult) -> None:
    out = apply_faults(clean, _scenario(encoder_spikes=5, encoder_spike_rad=0.5))
    diff = out.joints.positions_rad - clean.joints.positions_rad
    changed = np.nonzero(diff)[0]
    assert changed.size == 5 and np.allclose(np.abs(diff[changed]), 0.5)
    assert [s["index"] for s in out.faults["encoder_spikes"]] == changed.tolist()
    assert np.array_equal(out.joints.stamps_s, clean.joints.stamps_s)


def test_range_noise_scale() -> None:
    """Noise bands times k, the same noise draws: (r_k - r_0) = k (r_1 - r_0) up to the 1 mm quantisation."""
    s3 = _scenario(range_noise_scale=3.0)
    assert [b.sigma_m for b in scale_range_noise(s3).sensor.noise_bands] == pytest.approx([0.03, 0.09, 0.15])
    r0, r1, r3 = (simulate(_scenario(range_noise_scale=k)) for k in (0.0, 1.0, 3.0))
    assert r3.faults == {"range_noise_scale": 3.0}
    ok = np.isfinite(r0.ranges_m) & np.isfinite(r1.ranges_m) & np.isfinite(r3.ranges_m)
    e1, e3 = (r1.ranges_m - r0.ranges_m)[ok], (r3.ranges_m - r0.ranges_m)[ok]
    assert np.std(e1) > 0.005 and np.quantile(np.abs(e3 - 3 * e1), 0.99) <= 0.0041


def test_simulate_injects_and_records(clean: SimResult, tmp_path: Path) -> None:
    """simulate() applies the faults; ground_truth.yaml lists them."""
    scenario = _scenario(encoder_spikes=2, false_blobs=1, tape_outliers=[{"pair": 3, "error_m": -0.1}])
    out = simulate(scenario)
    again = apply_faults(clean, scenario)
    assert _same(out.intensities, again.intensities) and _same(out.joints.positions_rad, again.joints.positions_rad)
    assert _same(out.tape.distances_m, again.tape.distances_m)
    write_recording(out, scenario, tmp_path / "rec")
    gt = yaml.safe_load((tmp_path / "rec" / "ground_truth.yaml").read_text())
    assert set(gt["faults"]) == {"encoder_spikes", "false_blobs", "tape_outliers"}
    assert gt["faults"]["tape_outliers"][0]["row"] == 3 and len(gt["faults"]["encoder_spikes"]) == 2


def test_gear_ratio(clean: SimResult) -> None:
    out = apply_faults(clean, _scenario(gear_ratio=1.5))
    assert np.allclose(out.joints.positions_rad, 1.5 * clean.joints.positions_rad, rtol=0, atol=1e-15)
    assert np.allclose(out.joints.velocities_rad_s, 1.5 * clean.joints.velocities_rad_s, rtol=0, atol=1e-15)
    assert np.array_equal(out.joints.true_positions_rad, clean.joints.true_positions_rad)  # truth unchanged
    assert np.array_equal(out.beam_lambda_rad, clean.beam_lambda_rad) and out.faults == {"gear_ratio": 1.5}


def test_range_scale(clean: SimResult) -> None:
    """Every range and every echo's times k; the truth (the beams' motor angles, the bearings) unchanged."""
    out = apply_faults(clean, _scenario(range_scale=1.01))
    assert _same(out.ranges_m, clean.ranges_m * 1.01) and out.faults == {"range_scale": 1.01}
    if clean.echo_ranges_m is not None:
        assert out.echo_ranges_m is not None and _same(out.echo_ranges_m, clean.echo_ranges_m * 1.01)
    assert np.array_equal(out.beam_lambda_rad, clean.beam_lambda_rad) and np.array_equal(out.mu_rad, clean.mu_rad)
    assert apply_faults(clean, _scenario(range_scale=1.0)).faults == {}


@pytest.mark.parametrize(("rate_hz", "every"), [(30.0, 4), (50.0, 2), (100.0, 1), (1000.0, 1)])
def test_joint_rate(clean: SimResult, rate_hz: float, every: int) -> None:
    """The joint states thinned to every n-th sample, n = ceil(100 Hz / f): at most f."""
    out = apply_faults(clean, _scenario(joint_rate_hz=rate_hz))
    j, c = out.joints, clean.joints
    for name in ("stamps_s", "positions_rad", "velocities_rad_s", "true_positions_rad"):
        assert np.array_equal(getattr(j, name), getattr(c, name)[::every]), name
    assert 1.0 / np.diff(j.stamps_s).min() <= rate_hz * (1 + 1e-9)
    assert out.faults == {"joint_rate_hz": {"requested_hz": rate_hz, "keep_every": every, "rate_hz": 100.0 / every}}


def test_angle_increment_off_by_one(clean: SimResult) -> None:
    sensor = _scenario().sensor
    out = apply_faults(clean, _scenario(angle_increment_off_by_one=True))
    n = sensor.n_beams
    span = (n - 1) * sensor.angle_increment_rad
    assert out.declared_angle_increment_rad == pytest.approx(span / n, rel=1e-15)
    assert clean.declared_angle_increment_rad is None
    assert _same(out.ranges_m, clean.ranges_m) and np.array_equal(out.mu_rad, clean.mu_rad)  # the beams stay
    rec = out.faults["angle_increment_off_by_one"]
    assert rec["true_angle_increment_rad"] == sensor.angle_increment_rad
    assert rec["declared_angle_increment_rad"] == out.declared_angle_increment_rad


def test_new_faults_in_the_written_recording(clean: SimResult, tmp_path: Path) -> None:
    """gear_ratio, joint_rate_hz and angle_increment_off_by_one as the calibration's reader sees them: the joint
    positions scaled by k and thinned to every 4th sample (25 Hz), the LaserScans' declared increment span / N with
    angle_min and angle_max unchanged; the ranges as they were."""
    from rosbags.highlevel import AnyReader

    from lrfcal.errors import InputError
    from lrfcal.io.recording import read_recording
    from lrfcal.io.rig import ScanSource

    scenario = _scenario(gear_ratio=0.9, joint_rate_hz=30.0, angle_increment_off_by_one=True)
    out = apply_faults(clean, scenario)
    write_recording(out, scenario, tmp_path / "rec")
    with pytest.raises(InputError, match="scan.angles"):  # the scans' own fields disagree: the rig file must say
        read_recording(tmp_path / "rec")
    rec = read_recording(tmp_path / "rec", scan=ScanSource(angles="increment"))  # as the LaserScans declare it
    assert np.allclose(rec.joints.positions_rad, 0.9 * clean.joints.positions_rad[::4], rtol=0, atol=1e-12)
    assert np.allclose(np.diff(rec.joints.stamps_s), 0.04, atol=1e-6)
    s = scenario.sensor
    declared = (s.n_beams - 1) * s.angle_increment_rad / s.n_beams
    mu = rec.scans.mu_rad[0]
    assert np.diff(mu) == pytest.approx(declared, rel=1e-6)
    assert mu[-1] - mu[0] == pytest.approx((s.n_beams - 1) * declared, rel=1e-6)
    assert _same(rec.scans.ranges_m[:, :10], clean.ranges_m[:, :10].astype(np.float32))
    with AnyReader([tmp_path / "rec" / "bag"]) as reader:
        conn = next(c for c in reader.connections if c.topic == "/scan")
        _, _, raw = next(iter(reader.messages(connections=[conn])))
        msg = reader.deserialize(raw, conn.msgtype)
    assert msg.angle_min == pytest.approx(s.angle_min_rad, abs=1e-7)
    assert msg.angle_max == pytest.approx(s.angle_min_rad + (s.n_beams - 1) * s.angle_increment_rad, abs=1e-6)
    assert msg.angle_increment == pytest.approx(declared, rel=1e-6)
    gt = yaml.safe_load((tmp_path / "rec" / "ground_truth.yaml").read_text())
    assert set(gt["faults"]) == {"gear_ratio", "joint_rate_hz", "angle_increment_off_by_one"}


@pytest.mark.parametrize(
    ("faults", "field"),
    [({"false_blobs": -1}, "faults.false_blobs"), ({"dropped_scans_fraction": 0.95}, "dropped_scans_fraction"),
     ({"smoke": 1}, "faults.smoke"), ({"tape_outliers": [{"pair": 1}]}, "error_m"),
     ({"gear_ratio": 0.0}, "faults.gear_ratio"), ({"joint_rate_hz": -5}, "faults.joint_rate_hz"),
     ({"range_scale": 0.0}, "faults.range_scale")],
)
def test_faults_section_is_validated(faults: dict[str, Any], field: str) -> None:
    with pytest.raises(InputError, match=field):
        parse_scenario(_data(**faults), "test")


def test_tape_outlier_end_to_end(tmp_path: Path) -> None:
    """A misread tape (0.5 m on one pair) injected by the simulator is named and dropped by the calibration,
    whose marker map is then back at tape noise and whose DH parameters are within 4 sigma of the truth."""
    from lrfcal.io.calibration_yaml import calibration_dict
    from lrfcal.io.recording import read_recording
    from lrfcal.model.kinematics import DH_NAMES, PARAM_NAMES
    from lrfcal.pipeline import CalibConfig, calibrate
    from lrfcal.report.markdown import render_report

    data = _data(tape_outliers=[{"pair": ["m02", "m13"], "error_m": 0.5}])
    data["servo"].update({"start_rad": math.pi / 2, "end_rad": -math.pi / 2, "speed_rad_s": math.radians(30)})
    scenario = parse_scenario(data, "test")
    write_recording(simulate(scenario), scenario, tmp_path / "rec")
    result = calibrate(read_recording(tmp_path / "rec"), CalibConfig())
    (dropped,) = result.evidence.markers.dropped_pairs
    assert {dropped.id_i, dropped.id_j} == {"m02", "m13"} and abs(dropped.error_m - 0.5) < 0.005
    assert result.evidence.markers.rms_m < 0.002
    (written,) = calibration_dict(result)["marker_map"]["dropped_pairs"]
    assert set(written["pair"]) == {"m02", "m13"} and written["measured_m"] > written["predicted_m"] + 0.49
    assert "tape pair m02-m13 dropped" in render_report(result)
    sol = result.solution
    for name in DH_NAMES:
        err = getattr(sol.params.dh, name) - getattr(scenario.rig.dh, name)
        assert abs(err) <= 4 * sol.sigma[PARAM_NAMES.index(name)], (name, err)
