"""Stage 1: marker map from tape distances (classical MDS, weighted SMACOF, validation)."""

from __future__ import annotations

from itertools import combinations
from pathlib import Path

import numpy as np
import pytest
from conftest import tiered

from lrfcal.errors import CalibrationError, InputError
from lrfcal.stages.mds import marker_map
from lrfcal.types import TapeMeasurements
from lrfsim.scenario.file import load_scenario
from lrfsim.world.geometry import marker_centres_W


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


# --- gross errors: a misread tape is named and dropped, or the map refused ---------------------------------------

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def _layout(name: str) -> np.ndarray:
    """Marker centres (n, 3) of a shipped scenario: tunnel_v (18 markers, 3D), plane_0deg (25, a board)."""
    return marker_centres_W(load_scenario(SCENARIOS / f"{name}.yaml"))


def _with_errors(tape: TapeMeasurements, errors: dict[int, float]) -> TapeMeasurements:
    d = tape.distances_m.copy()
    for k, e in errors.items():
        d[k] += e
    return TapeMeasurements(tape.marker_ids, tape.pairs, d)


def _pair_ids(tape: TapeMeasurements, k: int) -> set[str]:
    return {tape.marker_ids[int(i)] for i in tape.pairs[k]}


@pytest.mark.parametrize("layout", ["tunnel_v", "plane_0deg"])
@pytest.mark.parametrize("error_m", [0.05, -0.5, 1.0])
def test_one_tape_outlier_is_named_and_dropped(layout: str, error_m: float) -> None:
    X = _layout(layout)
    clean = _tape(X, noise=0.001, seed=11)
    k = int(np.nonzero(clean.distances_m > 0.8)[0][3])  # the -0.5 m error keeps the distance positive
    mm = marker_map(_with_errors(clean, {k: error_m}))
    assert len(mm.dropped_pairs) == 1, mm.dropped_pairs
    dp = mm.dropped_pairs[0]
    assert {dp.id_i, dp.id_j} == _pair_ids(clean, k)
    assert abs(dp.error_m - error_m) < 0.005 and dp.z > 5
    assert mm.rms_m < 0.0015, mm.rms_m  # back at tape noise (1 mm); 35-70 mm with the outlier absorbed
    assert _procrustes_rms(mm.positions_W, X) < 0.003
    assert mm.coplanar == (layout == "plane_0deg")


@pytest.mark.parametrize("layout", ["tunnel_v", "plane_0deg"])
def test_two_tape_outliers_are_dropped(layout: str) -> None:
    X = _layout(layout)
    clean = _tape(X, noise=0.001, seed=12)
    bad = {5: 0.3, 60: -0.12}
    mm = marker_map(_with_errors(clean, bad))
    assert {frozenset((p.id_i, p.id_j)) for p in mm.dropped_pairs} == {
        frozenset(_pair_ids(clean, k)) for k in bad
    }
    assert mm.rms_m < 0.0015 and _procrustes_rms(mm.positions_W, X) < 0.003


def test_outlier_without_pairs_to_spare_is_refused() -> None:
    """Marker 7 is taped to 4 others only: one of those 4 wrong cannot be dropped (3 partners do not check
    it in 3D), so the map is refused, naming the pair and the marker."""
    X = _layout("tunnel_v")
    pairs = np.array(list(combinations(range(len(X)), 2)))
    partners = [0, 3, 11, 15]
    keep = ~(pairs == 7).any(1) | np.isin(pairs, partners).any(1) & (pairs == 7).any(1)
    tape = _tape(X, keep, noise=0.001, seed=13)
    k = int(np.nonzero((tape.pairs == 7).any(1) & (tape.pairs == 11).any(1))[0][0])
    assert int((tape.pairs == 7).any(1).sum()) == 4
    with pytest.raises(CalibrationError, match="cannot be dropped") as info:
        marker_map(_with_errors(tape, {k: 0.5}))
    msg = str(info.value)
    assert "m7" in msg and "m7-m11" in msg and "\n" not in msg
    assert info.value.exit_code == 3


def test_inconsistent_tape_is_refused() -> None:
    """Errors everywhere (20 mm tape noise): nothing stands out to drop, and the map is refused by its RMS."""
    X = _layout("tunnel_v")
    with pytest.raises(CalibrationError, match="RMS") as info:
        marker_map(_tape(X, noise=0.02, seed=14))
    assert "worst pairs" in str(info.value)


@pytest.mark.parametrize("seed", tiered(range(20), keep=6))
def test_no_false_drops_on_noise(seed: int) -> None:
    """1 mm tape noise only, on random 3D layouts, boards and incomplete pair sets: nothing is dropped."""
    rng = np.random.default_rng(100 + seed)
    n = int(rng.integers(8, 26))
    if seed % 3 == 0:  # a board
        X = np.c_[rng.uniform(-0.75, 0.75, (n, 2)), np.zeros(n)]
    else:  # markers in a tunnel-sized box
        X = rng.uniform([0.0, -0.4, 0.0], [2.5, 0.4, 2.3], (n, 3))
    keep = None
    if seed % 2 == 1:  # 80 % of the pairs
        P = n * (n - 1) // 2
        keep = rng.uniform(size=P) < 0.8
        pairs = np.array(list(combinations(range(n), 2)))
        deg = np.bincount(pairs[keep].ravel(), minlength=n)
        keep |= (deg[pairs] < 5).any(1)  # every marker keeps >= 5 partners
    mm = marker_map(_tape(X, keep, noise=0.001, seed=seed))
    assert mm.dropped_pairs == (), mm.dropped_pairs
    assert mm.rms_m < 0.002
