"""Stage 4: blob-to-marker association, mirror detection, Kabsch."""

from __future__ import annotations

import time

import numpy as np
import pytest

from lrfcal.association import associate, kabsch, unmirror
from lrfcal.errors import CalibrationError
from lrfcal.model.kinematics import pose_matrix, transform_points
from lrfcal.types import MarkerMap


def _random_T(rng: np.random.Generator) -> np.ndarray:
    return pose_matrix(*rng.uniform(-2, 2, 3), *rng.uniform(-np.pi, np.pi, 3))


def _map(X: np.ndarray) -> MarkerMap:
    return MarkerMap(tuple(f"m{i}" for i in range(len(X))), X, 0.0, 0.0, 0.5, False)


def _scene(
    rng: np.random.Generator, n: int = 30, missed: int = 5, passes: int = 2, false_frac: float = 0.3,
    noise: float = 0.005,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Markers X (n, 3) in W, blobs in M, the true T_W_M and the true blob labels (-1 false)."""
    X = rng.uniform(-1.5, 1.5, (n, 3))
    X -= X.mean(0)
    T = _random_T(rng)
    seen = np.sort(rng.choice(n, n - missed, replace=False))
    labels = np.repeat(seen, passes)
    Tinv = np.linalg.inv(T)
    blobs = transform_points(Tinv, X[labels]) + rng.normal(0, noise, (labels.size, 3))
    n_false = int(round(false_frac * labels.size / (1 - false_frac)))
    lo, hi = blobs.min(0), blobs.max(0)
    fake = rng.uniform(lo, hi, (n_false, 3))
    P = np.vstack([blobs, fake])
    lab = np.r_[labels, np.full(n_false, -1)]
    perm = rng.permutation(len(P))
    return X, P[perm], T, lab[perm]


def test_kabsch_exact_and_weighted() -> None:
    rng = np.random.default_rng(0)
    P = rng.normal(size=(10, 3))
    T = _random_T(rng)
    Q = transform_points(T, P)
    assert np.allclose(kabsch(P, Q), T, atol=1e-12)
    Q2 = Q.copy()
    Q2[0] += 5.0
    w = np.ones(10)
    w[0] = 0.0
    assert np.allclose(kabsch(P, Q2, w), T, atol=1e-12)
    # a reflection is never returned
    assert np.linalg.det(kabsch(P, P * [1, 1, -1])[:3, :3]) > 0


@pytest.mark.parametrize("seed", range(6))
def test_missing_false_and_doubled_blobs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    X, P, T, lab = _scene(rng)
    t0 = time.perf_counter()
    a = associate(P, _map(X), gate_m=0.05)
    assert time.perf_counter() - t0 < 1.0  # < 0.2 s typically; loose for slow CI machines
    assert not a.mirrored
    true = lab >= 0
    assert np.array_equal(a.blob_to_marker[true], lab[true])
    assert np.mean(a.blob_to_marker[~true] >= 0) < 0.1  # false blobs only matched by chance
    assert np.allclose(a.T_W_M[:3, :3], T[:3, :3], atol=5e-3)
    assert np.allclose(a.T_W_M[:3, 3], T[:3, 3], atol=5e-3)
    assert a.rms_m < 0.02 and a.n_matched >= true.sum()


@pytest.mark.parametrize("seed", range(3))
def test_mirrored_mds_frame(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    X, P, T, lab = _scene(rng, passes=1, false_frac=0.2)
    mirrored_map = _map(X * [1, 1, -1])  # MDS returned the mirror image of the real layout
    a = associate(P, mirrored_map)
    assert a.mirrored
    fixed = unmirror(mirrored_map)
    assert np.allclose(fixed.positions_W, X)
    true = lab >= 0
    assert np.array_equal(a.blob_to_marker[true], lab[true])
    assert np.allclose(a.T_W_M, T, atol=5e-3)


def test_coplanar_markers_not_mirrored() -> None:
    rng = np.random.default_rng(4)
    X = np.c_[rng.uniform(-1.5, 1.5, (15, 2)), np.zeros(15)]
    T = _random_T(rng)
    P = transform_points(np.linalg.inv(T), X[2:]) + rng.normal(0, 0.003, (13, 3))
    a = associate(P, _map(X))
    assert not a.mirrored
    assert np.array_equal(a.blob_to_marker, np.arange(2, 15))


def test_speed_40_blobs_30_markers() -> None:
    rng = np.random.default_rng(9)
    X, P, _, _ = _scene(rng, n=30, missed=2, passes=1, false_frac=0.3)
    P = P[:40]
    associate(P, _map(X))  # warm-up
    t0 = time.perf_counter()
    associate(P, _map(X))
    assert time.perf_counter() - t0 < 0.5


def test_nan_blobs_stay_unmatched() -> None:
    rng = np.random.default_rng(12)
    X, P, T, lab = _scene(rng, passes=1, false_frac=0.0)
    P[[0, 5]] = np.nan
    a = associate(P, _map(X))
    assert a.blob_to_marker[0] == -1 and a.blob_to_marker[5] == -1
    ok = np.ones(len(P), bool)
    ok[[0, 5]] = False
    assert np.array_equal(a.blob_to_marker[ok], lab[ok])


def test_too_few_blobs() -> None:
    X = np.random.default_rng(0).uniform(-1, 1, (6, 3))
    with pytest.raises(CalibrationError):
        associate(X[:2], _map(X))
