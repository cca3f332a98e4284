"""Sweeps, uncovered scans and per-scan layouts in lrfcal.commands.reproject.reproject_beams."""

from __future__ import annotations

import numpy as np

from lrfcal.commands.reproject import reproject_beams
from lrfcal.model.kinematics import DH, points_M
from lrfcal.stages.timing import sweep_passes
from lrfcal.types import JointStates, Scans


def test_sweep_index_splits_at_reversals_and_carries_over_standstills():
    lam = np.array([0.0, 0.0, 0.1, 0.2, 0.2, 0.3, 0.2, 0.1, 0.1, 0.0, 0.1])
    np.testing.assert_array_equal(sweep_passes(lam, min_fraction=0.0, min_scans=1), [0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2])
    assert sweep_passes(np.zeros(3), min_fraction=0.0, min_scans=1).tolist() == [0, 0, 0]


def test_reproject_beams_per_scan_layout_and_uncovered_scans():
    S, N = 6, 4
    stamps = 10.0 + 0.1 * np.arange(S)
    ranges = np.full((S, N), 2.0)
    ranges[1, 3] = np.nan  # a beam the scan did not carry
    mu = np.stack([np.linspace(-1, 1, N) * (1 if k % 2 else -1) for k in range(S)])  # negative increments too
    t_inc = np.where(np.arange(S) % 2, 1e-3, 2e-3)
    scans = Scans(stamps, ranges, np.ones((S, N)), mu, t_inc, 0.1, 0.01, 30.0,
                  beam_counts=np.array([4, 3, 4, 4, 4, 4]))
    jt = np.linspace(9.95, 10.35, 9)  # 50 ms samples: cover scans 0-3 only (scan 4 ends 6 ms after 10.40)
    joints = JointStates(jt, jt - 9.95)
    dh = DH(0.05, 0.2, 0.03, 0.1)
    c = reproject_beams(scans, joints, dh)
    assert c.n_scans_uncovered == 2 and set(c.scan.tolist()) == {0, 1, 2, 3} and len(c) == 15
    t = stamps[c.scan] + c.beam * t_inc[c.scan]
    lam = np.interp(t, joints.stamps_s, joints.positions_rad)
    np.testing.assert_allclose(c.points_M, points_M(2.0, lam, mu[c.scan, c.beam], dh), atol=1e-12)
    np.testing.assert_allclose(c.times_s, t)
    np.testing.assert_array_equal(c.scan_sweep[4:], [-1, -1])
    # a calibration's intrinsics act as in the model: the scanner reports range_scale r_true + range_offset, the
    # motor angle is motor_scale q, the bearing beam_scale mu
    intr = {"range_offset": 0.012, "range_scale": 1.01, "motor_scale": 0.98, "beam_scale": 1.001}
    c2 = reproject_beams(scans, joints, dh, intrinsics=intr)
    np.testing.assert_allclose(c2.points_M, points_M((2.0 - 0.012) / 1.01, 0.98 * lam, 1.001 * mu[c.scan, c.beam], dh),
                               atol=1e-12)


def test_calibration_intrinsics_are_read_only_when_estimated(tmp_path):
    """calibration.yaml's intrinsics section: the estimated ones (sigma not null); an older file without it gives its
    estimated range_offset_m; a name the model does not know is refused naming it."""
    import pytest

    from lrfcal.commands.reproject import read_calibration_intrinsics
    from lrfcal.errors import InputError

    new, old, held, bad = (tmp_path / f"{n}.yaml" for n in ("new", "old", "held", "bad"))
    new.write_text("intrinsics:\n  range_offset: {value: 0.0125, sigma: 0.0012}\n"
                   "  range_scale: {value: 1.01, sigma: 0.001}\n  motor_scale: {value: 1.0, sigma: null}\n")
    old.write_text("range_offset_m: {value: 0.0125, sigma: 0.0012}\n")
    held.write_text("range_offset_m: {value: 0.0, sigma: null}\n")
    bad.write_text("intrinsics:\n  gear: {value: 2.0, sigma: 0.1}\n")
    assert read_calibration_intrinsics(new) == {"range_offset": 0.0125, "range_scale": 1.01}
    assert read_calibration_intrinsics(old) == {"range_offset": 0.0125}
    assert read_calibration_intrinsics(held) == {}
    with pytest.raises(InputError, match="intrinsics.gear"):
        read_calibration_intrinsics(bad)


def test_simulated_recording_matches_the_pipelines_reprojection(tmp_path):
    """A small lrfsim recording read as a rig file says and reprojected beam by beam equals the calibration
    pipeline's own reprojection (lrfcal.stages.reproject with timing.beam_motor_angles, of the joint states with their
    quantisation taken out as lrfcal.stages.timing.usable_scans does) of the same recording."""
    import yaml
    from test_cli_sim import _write_small

    from lrfcal.io.recording import read_recording
    from lrfcal.stages.reproject import reproject_cloud
    from lrfcal.stages.timing import beam_motor_angles, covered_scans, without_quantisation
    from lrfsim.scenario.file import load_scenario
    from lrfsim.simulation.to_folder import simulate_to_folder

    simulate_to_folder(load_scenario(_write_small(tmp_path)), tmp_path / "rec")
    rec = read_recording(tmp_path / "rec", require_distances=False)
    assert rec.tape is None and rec.report is not None and rec.report.n_scans == rec.scans.stamps_s.size
    offset = float(yaml.safe_load((tmp_path / "rec" / "ground_truth.yaml").read_text())["clock_offset_s"])
    dh = DH(**yaml.safe_load((tmp_path / "rec" / "ground_truth.yaml").read_text())["dh"])
    c = reproject_beams(rec.scans, rec.joints, dh, offset)
    cov = covered_scans(rec.scans, rec.joints, offset)
    assert c.n_scans_uncovered == int((~cov).sum())
    from dataclasses import replace

    sub = replace(rec.scans, stamps_s=rec.scans.stamps_s[cov], ranges_m=rec.scans.ranges_m[cov],
                  intensities=rec.scans.intensities[cov], mu_rad=rec.scans.mu_rad[cov],
                  time_increment_s=rec.scans.time_increment_s[cov], beam_counts=rec.scans.beam_counts[cov])
    ref, inten = reproject_cloud(sub, beam_motor_angles(sub, without_quantisation(rec.joints, sub), offset), dh)
    assert len(c) == len(ref) > 10_000
    np.testing.assert_allclose(c.points_M, ref, atol=1e-9)
    np.testing.assert_array_equal(c.intensity, inten)


def test_clouds_with_shared_bearings_take_each_beams_trig_once_bit_for_bit(monkeypatch) -> None:
    """When every scan has the same bearings, reproject_clouds takes cos and sin of each beam's phi once and gathers
    them: the same clouds, bit for bit, as from every return's own phi; with per-scan bearings it takes those."""
    import lrfcal.stages.reproject as rp

    rng = np.random.default_rng(3)
    S, N = 40, 181
    ranges = rng.uniform(0.5, 8.0, (S, N))
    ranges[rng.random((S, N)) < 0.1] = np.nan
    mu = np.linspace(-2.0, 2.0, N)
    scans = Scans(stamps_s=np.arange(S) * 0.025, ranges_m=ranges, intensities=np.ones((S, N)), mu_rad=mu,
                  time_increment_s=1e-5, scan_time_s=0.025, range_min_m=0.1, range_max_m=30.0)
    lam = rng.uniform(-1.5, 1.5, (S, N))
    dhs = (DH(a=0.02, alpha=1.3, b=0.05, beta=0.1), DH(a=0.021, alpha=1.31, b=0.049, beta=0.11))
    intr = ({}, {"range_offset": 0.003, "beam_scale": 1.001})
    assert rp._shared_bearings(np.asarray(scans.mu_rad)) is not None
    clouds, _ = rp.reproject_clouds(scans, lam, dhs, 1, intr)
    monkeypatch.setattr(rp, "_shared_bearings", lambda mu: None)  # every return's own phi
    each, _ = rp.reproject_clouds(scans, lam, dhs, 1, intr)
    assert all(a.tobytes() == b.tobytes() for a, b in zip(clouds, each, strict=True))
    per_scan = np.asarray(scans.mu_rad).copy()
    per_scan[3] += 1e-9  # one scan's bearings differ: no shared row
    assert rp._shared_bearings(per_scan) is None
