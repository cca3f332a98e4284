"""Sweeps, uncovered scans and per-scan layouts in lrfcal.cloud.reproject_beams."""

from __future__ import annotations

import numpy as np

from lrfcal.cloud import reproject_beams, sweep_index
from lrfcal.kinematics import DH, points_M
from lrfcal.types import JointStates, Scans


def test_sweep_index_splits_at_reversals_and_carries_over_standstills():
    lam = np.array([0.0, 0.0, 0.1, 0.2, 0.2, 0.3, 0.2, 0.1, 0.1, 0.0, 0.1])
    np.testing.assert_array_equal(sweep_index(lam), [0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2])
    assert sweep_index(np.zeros(3)).tolist() == [0, 0, 0]


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
