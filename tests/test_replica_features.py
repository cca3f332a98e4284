"""The simulator's features for the replicas of real rigs (issue 54): step and scan (``servo.mode: step``), noise in
proportion to the range (``sensor.noise_range_fraction``), cylinders and spheres in the scene, the stand fixed to
the motor frame and seen by the laser (``rig.stand``), and the wiggles of the range along the scan and in range
(``sensor.systematic.beam_wiggle_m``, ``range_wiggle_m``), each against its documented model."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from lrfcal import pipeline
from lrfcal.config import DEFAULT_NOMINAL_TOLERANCE, CalibConfig
from lrfcal.errors import InputError
from lrfcal.io.calibration_yaml import _rig_dict
from lrfcal.io.recording import read_nominal, read_recording
from lrfcal.io.rig import parse_rig
from lrfcal.model.kinematics import Params, beam_rays_W, points_M
from lrfcal.stages.timing import scan_angles
from lrfsim.scenario.file import Scenario, parse_scenario, with_changes
from lrfsim.scenario.servo_timing import servo_run_time_s
from lrfsim.sensors import lidar
from lrfsim.sensors.servo import joint_samples, servo_trajectory, step_scan_phase_s
from lrfsim.simulation.faults import scale_range_noise
from lrfsim.simulation.recording import nominal_yaml, write_recording
from lrfsim.simulation.simulate import simulate, systematic_truth
from lrfsim.trials.variants import TRUTH_HALF_WIDTH, drawn_truth
from lrfsim.world.scene import build_scene

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
EXACT = {"sensor.noise": False, "sensor.footprint_rays": 1, "sensor.quantisation_m": 0.0,
         "sensor.systematic.beam_wiggle_m": 0.0}
#: the room replica tilting 0 -> 12 deg in 1.5 deg steps (10 scans: one before the 8 steps, one after each)
FEW_STEPS = {"servo.end_rad": math.radians(12.0), "servo.step_rad": math.radians(1.5), "servo.speed_rad_s": 5.0,
             "servo.settle_s": 0.1}


def _room(**changes: Any) -> Scenario:
    data = yaml.safe_load((SCENARIOS / "urg_room_90.yaml").read_text())
    return parse_scenario(with_changes(data, {**FEW_STEPS, **changes}), "test")


def _refused(**changes: Any) -> str:
    """The one line that refuses the room replica with ``changes``, as the scenario is read or its scene built."""
    with pytest.raises(InputError) as e:
        build_scene(_room(**changes))
    return str(e.value)


# --- step and scan ---------------------------------------------------------------------------------------------

def test_step_and_scan_stands_still_while_the_laser_scans(tmp_path: Path) -> None:
    sc = _room(**EXACT)
    traj = servo_trajectory(sc.servo)
    assert traj.end_s == servo_run_time_s(sc.servo)  # bit for bit
    result = simulate(sc)
    lam = result.beam_lambda_rad
    assert lam.shape[0] == 10 and np.all(lam == lam[:, :1])  # every beam of a scan at one angle
    steps = np.diff(lam[:, 0])  # one step between two scans (none across the holds at the ends)
    assert np.all((np.abs(steps) < 1e-15) | (np.abs(steps - math.radians(1.5)) < 1e-12))
    assert np.count_nonzero(np.abs(steps) > 1e-15) == 8
    assert math.isclose(lam[-1, 0], math.radians(12.0), abs_tol=1e-12)
    # every scan centred in its step's standstill: the move ends before the first beam, the next starts after the last
    first, last = result.scan_stamps_s, result.scan_stamps_s + (sc.sensor.n_beams - 1) * sc.sensor.time_increment_s
    t = np.linspace(first, last, 50).T
    np.testing.assert_array_equal(traj.velocity(t), 0.0)
    assert math.isclose(step_scan_phase_s(sc.servo, sc.sensor), result.scan_stamps_s[0], abs_tol=1e-12)
    # one joint state per scan, at its stamp, the stand's angle
    js = result.joints
    np.testing.assert_array_equal(js.stamps_s, result.scan_stamps_s)
    np.testing.assert_allclose(js.positions_rad, lam[:, 0], atol=1e-12)
    with pytest.raises(ValueError, match="one joint state per scan"):
        joint_samples(traj, sc.servo)
    # the recording declares it, and lrfcal reads every beam of a scan at the scan's angle
    assert yaml.safe_load(nominal_yaml(sc, None))["servo"]["motion"] == "step"
    rec = read_recording(write_recording(result, sc, tmp_path / "rec"), require_distances=False)
    assert rec.scans.angle_per_scan
    np.testing.assert_allclose(scan_angles(rec.scans, rec.joints), lam[:, 0], atol=1e-12)


def test_step_and_scan_refuses_a_stand_that_would_move_while_scanning() -> None:
    assert "must equal sensor.scan_period_s" in _refused(**{"servo.step_period_s": 0.2, "servo.settle_s": 0.2})
    assert "the servo would move while the laser scans" in _refused(**{"servo.speed_rad_s": 0.1})
    assert "whole number of steps" in _refused(**{"servo.end_rad": math.radians(12.7)})
    assert "whole number of step_period_s" in _refused(**{"servo.settle_s": 0.15})


# --- range noise in proportion to the range ---------------------------------------------------------------------

def _cast(ranges: np.ndarray) -> lidar.Cast:
    return lidar.Cast(ranges_m=ranges, intensities=np.full(ranges.shape, 1000.0), n_rays=0, n_calls=0,
                      cast_time_s=0.0, total_time_s=0.0, max_origin_error_m=0.0, max_parallax_correction_m=0.0,
                      cutoff_m=10.0)


def test_noise_grows_in_proportion_to_the_range() -> None:
    sensor = _room(**{"sensor.noise_correlation": 0.0, "sensor.quantisation_m": 0.0}).sensor
    assert sensor.noise_range_fraction == 0.003 and sensor.noise_bands[0].sigma_m == 0.0055
    r = np.array([0.5, 1.0, 1.8, 3.0, 5.0])
    np.testing.assert_allclose(lidar.range_sigma(r, sensor), np.maximum(0.0055, 0.003 * r))
    assert lidar.typical_range_sigma(np.array([1.0, 3.0, 5.0]), sensor) == pytest.approx(0.009)
    for true in (0.5, 4.0):
        out = lidar.sensor_model(_cast(np.full((400, 500), true)), sensor, np.random.default_rng(1))
        assert np.std(out.ranges_m - true) == pytest.approx(max(0.0055, 0.003 * true), rel=0.02)
    scaled = scale_range_noise(_room(**{"faults.range_noise_scale": 2.0}))  # a fault scales both
    assert scaled.sensor.noise_range_fraction == pytest.approx(0.006)


# --- cylinders, spheres and the stand ---------------------------------------------------------------------------

def _rays(result: Any, sc: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every beam's origin and direction in W (S N, 3) with the truth, and its simulated range (S N,)."""
    lam = result.beam_lambda_rad.ravel()
    mu = np.broadcast_to(result.mu_rad, result.beam_lambda_rad.shape).ravel()
    o, d = beam_rays_W(Params(sc.rig.mount.to_pose(), sc.rig.dh.to_dh()), lam, mu)
    return o, d, result.ranges_m.ravel()


def test_cylinder_and_sphere_ranges_are_exact() -> None:
    """A person-sized cylinder and a sphere in an empty room: every beam that meets one first returns its exact
    distance (ray-cylinder and ray-sphere intersections), but for a few grazing ones too faint to return."""
    cyl = {"pose": {"x": 0.0, "y": -0.5, "z": 0.85}, "radius_m": 0.15, "height_m": 1.7}
    sph = {"center_m": [0.2, 0.6, 1.0], "radius_m": 0.25}
    sc = _room(**EXACT, **{"scene.boxes": [], "scene.cylinders": [cyl], "scene.spheres": [sph], "rig.stand": []})
    o, d, r = _rays(simulate(sc), sc)
    # the cylinder (axis along z_W): the nearer root of |(o + t d - c)_xy| = R, within its height
    c = np.array([0.0, -0.5])
    oc, dxy = o[:, :2] - c, d[:, :2]
    A, B, C = (dxy**2).sum(1), 2 * (oc * dxy).sum(1), (oc**2).sum(1) - 0.15**2
    disc = B**2 - 4 * A * C
    t_cyl = np.where(disc > 0, (-B - np.sqrt(np.maximum(disc, 0))) / (2 * A), np.inf)
    z = o[:, 2] + t_cyl * d[:, 2]
    t_cyl[(t_cyl <= 0) | (z < 0) | (z > 1.7)] = np.inf
    oc3 = o - np.array(sph["center_m"])
    b3 = (oc3 * d).sum(1)
    disc3 = b3**2 - ((oc3**2).sum(1) - 0.25**2)
    t_sph = np.where(disc3 > 0, -b3 - np.sqrt(np.maximum(disc3, 0)), np.inf)
    t_sph[t_sph <= 0] = np.inf
    for t in (t_cyl, t_sph):
        hit = np.isfinite(t) & (t < np.minimum(t_cyl, t_sph) + 1e-12)  # this shape first (the walls are farther)
        returned = hit & np.isfinite(r)
        assert returned.sum() > 50 and returned.sum() >= 0.98 * hit.sum()
        np.testing.assert_allclose(r[returned], t[returned], atol=1e-9)


def test_the_stand_moves_with_the_mount_and_is_seen_at_large_tilts() -> None:
    """The stand's base board, fixed to the motor frame M: the returns on it lie on its top face in M whatever the
    mount, and appear only once the tilt passes about 45 deg."""
    changes = {**EXACT, "servo.end_rad": math.radians(81.0), "servo.step_rad": math.radians(4.5)}
    sc = _room(**changes)
    result = simulate(sc)
    on = np.isfinite(result.ranges_m) & (result.ranges_m < 0.16)
    tilt = np.broadcast_to(result.beam_lambda_rad, on.shape)
    assert on.sum() > 100 and tilt[on].min() > math.radians(40)
    s, b = np.nonzero(on)
    p = points_M(result.ranges_m[s, b], result.beam_lambda_rad[s, b], result.mu_rad[b], sc.rig.dh.to_dh())
    base = sc.rig.stand[0]
    top = base.pose.y - base.size_y_m / 2  # y_M points down: the board's top face
    on_top = np.abs(p[:, 1] - top) < 1e-9
    assert on_top.mean() > 0.5 and np.all(np.abs(p[on_top, 0] - base.pose.x) <= base.size_x_m / 2 + 1e-9)
    # the same returns with the mount moved: the stand goes with it
    moved = simulate(_room(**changes, **{"rig.mount.x": -1.0, "rig.mount.yaw": 0.3}))
    np.testing.assert_allclose(moved.ranges_m[on], result.ranges_m[on], atol=1e-9)


def test_the_optical_centre_inside_a_new_solid_is_refused() -> None:
    assert "is inside rig.stand[0]" in _refused(**{"rig.stand": [{"pose": {"y": -0.08}, "size_x_m": 0.1,
                                                                     "size_y_m": 0.1, "size_z_m": 0.1}]})
    cyl = {"pose": {"x": -1.8, "y": 0.0, "z": 1.1}, "radius_m": 0.2, "height_m": 0.5}
    assert "is inside scene.cylinders[0]" in _refused(**{"scene.cylinders": [cyl]})
    assert "is inside scene.spheres[0]" in _refused(**{"scene.spheres": [{"center_m": [-1.8, 0.0, 1.2],
                                                                            "radius_m": 0.3}]})


# --- wiggles of the range ---------------------------------------------------------------------------------------

def test_wiggles_along_the_scan_and_in_range() -> None:
    sensor = _room(**{"sensor.systematic.range_wiggle_m": 0.002, "sensor.systematic.range_wiggle_period_m": 0.4}
                   ).sensor
    ranges = np.array([[0.3, 1.0, 2.55] + [1.0] * (sensor.n_beams - 3)] * 2)
    bias = lidar.systematic_bias_m(np.full(ranges.shape, 500.0), sensor, ranges_m=ranges)
    i = np.arange(sensor.n_beams)
    expect = 0.0012 * np.sin(2 * np.pi * i / 61.0) + 0.002 * np.sin(2 * np.pi * ranges / 0.4)
    np.testing.assert_allclose(bias, expect, atol=1e-15)
    truth = systematic_truth(sensor)
    assert truth == {"beam_wiggle_m": 0.0012, "range_wiggle_m": 0.002, "beam_wiggle_period_beams": 61.0,
                     "range_wiggle_period_m": 0.4}
    # in a simulation, noise-free: each beam's range off the exact one by its wiggle, the same in every scan
    sc = _room(**{**EXACT, "sensor.systematic.beam_wiggle_m": 0.0012})
    exact = simulate(_room(**EXACT))
    wiggled = simulate(sc)
    both = np.isfinite(exact.ranges_m) & np.isfinite(wiggled.ranges_m)
    diff = np.where(both, wiggled.ranges_m - exact.ranges_m, np.nan)
    np.testing.assert_allclose(diff[both], np.broadcast_to(0.0012 * np.sin(2 * np.pi * i / 61.0), diff.shape)[both],
                               atol=1e-12)
    off = _room(**EXACT).sensor
    assert lidar.systematic_bias_m(np.full((2, 3), 500.0), off, ranges_m=np.ones((2, 3))) is None


# --- the truth drawn per trial (lrfsim study --truth-spread) ---------------------------------------------------

def test_drawn_truth_stays_around_the_nominal() -> None:
    sc = _room()
    nominal = sc.rig.nominal_dh
    drawn = [drawn_truth(sc, seed, 1.0).rig.dh for seed in range(200)]
    for p, w in TRUTH_HALF_WIDTH.items():
        d = np.array([getattr(t, p) - getattr(nominal, p) for t in drawn])
        assert np.all(np.abs(d) <= w) and np.ptp(d) > 1.5 * w  # within the half-width, and spread over it
    assert drawn_truth(sc, 7, 1.0) == drawn_truth(sc, 7, 1.0) and drawn_truth(sc, 7, 0.0) is sc
    assert drawn_truth(sc, 7, 1.0).rig.nominal_dh == nominal and drawn_truth(sc, 7, 1.0).rig.mount == sc.rig.mount


def test_drawn_truth_tells_the_calibration_how_well_the_nominal_knows_it(tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """A drawn truth's spread (uniform in +-scale x TRUTH_HALF_WIDTH) is the nominal's 1-sigma the rig file declares
    (``dh_tolerance``, its half width / sqrt 3); the calibration takes it (the consider covariance, the cost's prior,
    the checks' scale) unless its caller gives one, and writes it into the rig it saves (for `lrfcal check`)."""
    sc = drawn_truth(_room(), 7, 2.0)
    tol = sc.rig.nominal_dh_tolerance
    assert tol is not None
    declared = tuple(2.0 * w / math.sqrt(3.0) for w in TRUTH_HALF_WIDTH.values())
    np.testing.assert_allclose([tol.a, tol.alpha, tol.b, tol.beta], declared, rtol=1e-12)
    (tmp_path / "nominal.yaml").write_text(nominal_yaml(sc, None))
    rig = read_nominal(tmp_path / "nominal.yaml")
    assert rig.dh_tolerance is not None
    np.testing.assert_allclose(rig.dh_tolerance, declared, rtol=1e-12)
    assert parse_rig(_rig_dict(rig), "saved").dh_tolerance == parse_rig(
        yaml.safe_load((tmp_path / "nominal.yaml").read_text()), "written").dh_tolerance

    class Seen(Exception):
        pass

    def capture(recording: Any, config: CalibConfig, observer: Any) -> None:
        raise Seen(config.nominal_tolerance)

    monkeypatch.setattr(pipeline, "_calibrate", capture)

    def used(nominal: Any, config: CalibConfig) -> tuple[float, ...]:
        with pytest.raises(Seen) as e:
            pipeline.calibrate(SimpleNamespace(nominal=dataclasses.replace(nominal, range_pattern=False), report=None),
                               config)  # type: ignore[arg-type]
        return tuple(e.value.args[0])

    assert used(rig, CalibConfig()) == rig.dh_tolerance
    mine = (0.001, 0.01, 0.002, 0.02)
    assert used(rig, CalibConfig(dh_tolerance=mine)) == mine
    assert used(dataclasses.replace(rig, dh_tolerance=None), CalibConfig()) == DEFAULT_NOMINAL_TOLERANCE
    assert drawn_truth(_room(), 7, 0.0).rig.nominal_dh_tolerance is None  # nothing drawn: nothing declared


def test_a_rig_file_tolerance_in_millimetres_or_degrees_is_refused_naming_it() -> None:
    dh = {"a": 0.0, "alpha": 1.5708, "b": 0.08, "beta": 0.0}
    for key, value, unit in (("a", 3.0, "millimetres"), ("beta", 2.0, "degrees"), ("b", 0.0, "greater than 0")):
        tol = {"a": 0.003, "alpha": 0.02, "b": 0.003, "beta": 0.02, key: value}
        with pytest.raises(InputError) as e:
            parse_rig({"dh": dh, "dh_tolerance": tol}, "rig/nominal.yaml")
        line = str(e.value)
        assert "\n" not in line and line.startswith(f"rig/nominal.yaml: dh_tolerance.{key}: ") and unit in line, line


def test_a_study_of_a_marker_less_scenario_calibrates_each_drawn_truth_as_a_user(monkeypatch: pytest.MonkeyPatch
                                                                                 ) -> None:
    """`lrfsim study --truth-spread 1` of a marker-less scenario: every trial simulates its own drawn truth and hands
    the recording to lrfsim.trials.trial.calibrate_as_user (what `lrfcal calibrate --targetless` runs; stubbed here
    to read back the truth the recording carries), and a held parameter (sigma NaN) counts in no RMS."""
    from lrfsim.trials import study as study_module
    from lrfsim.trials import trial as trial_module
    from lrfsim.trials.compare import load_truth
    from lrfsim.trials.study_result import summary_markdown

    seen: list[tuple[float, ...]] = []

    def stub(folder: Path, *, name: str | None = None, keep_result: bool = False, force: bool = False
             ) -> trial_module.Trial:
        dh = load_truth(folder / "ground_truth.yaml").dh
        seen.append((dh.a, dh.alpha, dh.b, dh.beta))
        assert not (folder / "distances.csv").exists() and not force
        return trial_module.Trial(name or "", "calibrated", np.array([0.001, 0.0, 0.002, 0.0]),
                                  np.array([np.nan, 0.001, 0.001, 0.001]))

    monkeypatch.setattr(trial_module, "calibrate_as_user", stub)
    sc = _room(**{"servo.end_rad": math.radians(3.0)})
    s = study_module.study(sc, 2, seed0=5, truth_spread=1.0)
    drawn = [drawn_truth(sc, seed, 1.0).rig.dh for seed in (5, 6)]
    np.testing.assert_allclose(seen, [(t.a, t.alpha, t.b, t.beta) for t in drawn], atol=1e-12)
    st = s.parts[0].stats()
    assert st["a"]["n"] == 0 and math.isnan(st["a"]["rms_z"]) and st["b"]["rms_z"] == pytest.approx(2.0)
    text = summary_markdown(s)
    assert "Drawn truth (scale 1)" in text
    # no plan (targetless) and a held in every trial: its ratios are "-", never "nan"
    assert "nan" not in text and "| a | " in text and "| b | " in text
