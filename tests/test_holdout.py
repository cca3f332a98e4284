"""lrfcal.stages.holdout: the targetless calibration's check on returns it did not use."""

from __future__ import annotations

import numpy as np

from lrfcal.stages.holdout import HOLDOUT_EVERY, held_out_flatness, held_out_scans


def _box_cloud(rng: np.random.Generator, noise_m: float = 0.004) -> np.ndarray:
    """Returns (P, 3) on three faces of a 4 x 3 x 2.5 m room, with range-like noise."""
    n = 4000
    floor = np.c_[rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), np.full(n, -1.0)]
    wall = np.c_[np.full(n, 2.0), rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.5, n)]
    side = np.c_[rng.uniform(-2, 2, n), np.full(n, 1.5), rng.uniform(-1.0, 1.5, n)]
    return np.vstack([floor, wall, side]) + rng.normal(0.0, noise_m, (3 * n, 3))


def test_thicker_held_out_planes_fail_and_equal_or_thinner_pass() -> None:
    rng = np.random.default_rng(3)
    nominal = _box_cloud(rng)
    same = held_out_flatness(nominal, nominal.copy(), thickness_m=0.05)
    assert same.available and same.passed and same.n_planes == 3
    assert abs(same.thickness_nominal_m - 0.004) < 0.0006  # the noise, measured robustly
    # the "calibrated" cloud bent by a wrong parameter: a rotation that grows with the height (a bad DH bends planes)
    z = nominal[:, 2:3]
    bent = nominal + 0.01 * np.c_[np.sin(2 * z), np.cos(3 * z), np.sin(z)] * (z - z.mean())
    worse = held_out_flatness(nominal, bent, thickness_m=0.05)
    assert worse.thickness_calibrated_m > worse.thickness_nominal_m + worse.limit_m
    assert not worse.passed and "thicker" in worse.detail()
    better = held_out_flatness(bent, nominal, thickness_m=0.05)  # the calibration undoes the bend
    assert better.passed and better.thickness_calibrated_m < better.thickness_nominal_m


def test_nothing_to_judge_is_said() -> None:
    rng = np.random.default_rng(4)
    scatter = rng.uniform(-1, 1, (300, 3))
    h = held_out_flatness(scatter, scatter, thickness_m=0.01)
    assert not h.available and h.passed and "not available" in h.detail()


def test_held_out_scans_are_every_fifth_over_the_whole_sweep() -> None:
    m = held_out_scans(23)
    assert m.sum() == 4 and np.all(np.flatnonzero(m) % HOLDOUT_EVERY == HOLDOUT_EVERY - 1)
