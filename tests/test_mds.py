"""Stage 1: marker map from tape distances (classical MDS, weighted SMACOF, validation)."""

from __future__ import annotations

from itertools import combinations

import numpy as np
import pytest

from lrfcal.errors import InputError
from lrfcal.mds import marker_map
from lrfcal.types import TapeMeasurements


def _tape(
    X: np.ndarray, keep: np.ndarray | None = None, noise: float = 0.0, seed: int = 0
) -> TapeMeasurements:
    pairs = np.array(list(combinations(range(len(X)), 2)), dtype=np.int64)
    if keep is not None:
        pairs = pairs[keep]
    d = np.linalg.norm(X[pairs[:, 0]] - X[pairs[:, 1]], axis=1)
    d = d + np.random.default_rng(seed).normal(0.0, noise, d.size)
    return TapeMeasurements(tuple(f"m{i}" for i in range(len(X))), pairs, d)


def _procrustes_rms(A: np.ndarray, B: np.ndarray) -> float:
    """RMS after the best rigid motion, reflections allowed (orthogonal Procrustes)."""
    A0, B0 = A - A.mean(0), B - B.mean(0)
    U, _, Vt = np.linalg.svd(A0.T @ B0)
    return float(np.sqrt(np.mean(((A0 @ U @ Vt) - B0) ** 2) * 3))


def test_exact_recovery_complete_noiseless() -> None:
    X = np.random.default_rng(0).uniform(-2, 2, (12, 3))
    mm = marker_map(_tape(X))
    assert _procrustes_rms(mm.positions_W, X) < 1e-9
    assert mm.stress < 1e-12 and mm.rms_m < 1e-9 and not mm.coplanar
    assert np.allclose(mm.positions_W.mean(0), 0.0, atol=1e-12)
    # principal axes: the coordinates' covariance is diagonal, largest spread first
    C = np.cov(mm.positions_W.T)
    assert np.allclose(C - np.diag(np.diag(C)), 0.0, atol=1e-9) and C[0, 0] >= C[1, 1] >= C[2, 2]


def test_smacof_with_30_percent_missing() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform(-2, 2, (15, 3))
    P = 15 * 14 // 2
    keep = np.ones(P, bool)
    keep[rng.choice(P, int(0.3 * P), replace=False)] = False
    # noiseless: exact
    tape = _tape(X, keep)
    assert len(tape.pairs) < P
    mm = marker_map(tape)
    assert _procrustes_rms(mm.positions_W, X) < 1e-6
    # 2 mm tape noise: recovered within noise
    mm = marker_map(_tape(X, keep, noise=0.002, seed=3))
    assert _procrustes_rms(mm.positions_W, X) < 0.004
    assert 0.0005 < mm.rms_m < 0.003 and mm.stress < 0.01


def test_noisy_complete_within_noise() -> None:
    rng = np.random.default_rng(2)
    X = rng.uniform(-2, 2, (10, 3))
    mm = marker_map(_tape(X, noise=0.002, seed=5))
    assert _procrustes_rms(mm.positions_W, X) < 0.004


def test_coplanar_flag() -> None:
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-2, 2, (10, 2)), rng.normal(0, 0.005, 10)]
    mm = marker_map(_tape(X, noise=0.001))
    assert mm.coplanar and mm.planarity < 0.02
    # the plane's normal is z; out of the plane 1 mm of tape noise becomes cm (d ~ sqrt(dxy^2 + dz^2))
    assert np.abs(mm.positions_W[:, 2]).max() < 0.1
    X3 = rng.uniform(-2, 2, (10, 3))
    assert not marker_map(_tape(X3)).coplanar


def _one_line() -> str:
    return "\n"


@pytest.mark.parametrize(
    ("case", "match"),
    [
        ("three", "at least 4 markers"),
        ("partners", "partner"),
        ("line", "one line"),
        ("negative", "positive"),
        ("zero", "positive"),
        ("self", "itself"),
    ],
)
def test_validation_errors(case: str, match: str) -> None:
    rng = np.random.default_rng(4)
    X = rng.uniform(-1, 1, (6, 3))
    if case == "three":
        tape = _tape(X[:3])
    elif case == "partners":
        pairs = np.array(list(combinations(range(6), 2)))
        keep = ~((pairs == 5).any(1) & ~np.isin(pairs, [0, 1]).any(1))  # marker 5 measured to 0 and 1 only
        tape = _tape(X, keep)
    elif case == "line":
        t = rng.uniform(-1, 1, 6)
        tape = _tape(np.c_[t, 2 * t, -t])
    else:
        tape = _tape(X)
        d = tape.distances_m.copy()
        pairs = tape.pairs.copy()
        if case == "negative":
            d[3] = -0.5
        elif case == "zero":
            d[3] = 0.0
        else:
            pairs[3] = (2, 2)
        tape = TapeMeasurements(tape.marker_ids, pairs, d)
    with pytest.raises(InputError, match=match) as info:
        marker_map(tape)
    assert _one_line() not in str(info.value)
