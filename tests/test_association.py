"""Stage 4: blob-to-marker association, mirror detection, Kabsch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lrfcal.errors import CalibrationError
from lrfcal.model.kinematics import pose_matrix, transform_points
from lrfcal.stages.association import associate, kabsch, unmirror
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
    a = associate(P, _map(X), gate_m=0.05)
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


def test_40_blobs_30_markers_one_pass() -> None:
    """40 blobs of one pass (30 % false) on 30 markers: the true blobs matched (its speed: benchmarks/)."""
    rng = np.random.default_rng(9)
    X, P, _, lab = _scene(rng, n=30, missed=2, passes=1, false_frac=0.3)
    a = associate(P[:40], _map(X))
    true = lab[:40] >= 0
    assert true.sum() >= 10 and np.mean(a.blob_to_marker[true] == lab[:40][true]) >= 0.9


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


@pytest.mark.parametrize("seed", [0, 1])
def test_branch_and_bound_keeps_exactly_the_best_hypotheses(seed: int) -> None:
    """The search's top k (lrfcal.stages.association._best_hypotheses: probe blobs, then the rest block by block, each
    hypothesis dropped once its bound falls below the k-th best full score) is exactly the top k of scoring every
    hypothesis on every blob, also with near-copies of the true pose whose scores tie or nearly tie."""
    from scipy.spatial.transform import Rotation

    from lrfcal.stages.association import _best_hypotheses, _score

    rng = np.random.default_rng(seed)
    X = rng.uniform(-2.0, 2.0, size=(30, 3))  # markers
    R_true = Rotation.random(random_state=seed).as_matrix()
    t_true = rng.normal(size=3)
    P = (np.vstack([X, X[:20]]) - t_true) @ R_true  # blobs: X = R P + t (20 markers seen twice)
    P += rng.normal(0.0, 0.003, P.shape)
    P[40:] = rng.uniform(-2.0, 2.0, size=(10, 3))  # 10 blobs that are no marker
    w = rng.uniform(0.5, 1.5, len(P))
    H = 3000
    R = Rotation.random(H, random_state=seed + 10).as_matrix()
    t = rng.normal(size=(H, 3))
    near = rng.choice(H, 40, replace=False)  # near-copies of the truth: the top k must be chosen among them
    R[near] = Rotation.from_rotvec(rng.normal(0.0, 0.002, (40, 3))).as_matrix() @ R_true
    t[near] = t_true + rng.normal(0.0, 0.004, (40, 3))
    t[near[:5]] = t_true  # exact ties in score among some
    R[near[:5]] = R_true
    score, rms = _score(R, t, P, X, w, 0.02)
    for k in (1, 5, 12):
        np.testing.assert_array_equal(_best_hypotheses(R, t, P, X, w, 0.02, k=k), np.lexsort((rms, -score))[:k])
        # the block-by-block pruning alone: every hypothesis whose full score reaches a threshold survives it, and
        # most of those that cannot are dropped
        from lrfcal.stages.association import _reaching

        probe = np.arange(0, len(P), 7)
        part, _ = _score(R, t, P[probe], X, w[probe], 0.02)
        for kth in np.sort(score)[::-1][[3, 20, 39]]:  # among the near-copies' scores
            kept = _reaching(lambda c, b: _score(R[c], t[c], P[b], X, w[b], 0.02)[0], w, np.arange(H), probe, part,
                             float(kth))
            assert set(np.flatnonzero(score >= kth)) <= set(kept.tolist())
            assert kept.size < 100, kept.size  # the random poses cannot reach it and are dropped


def test_pair_score_does_not_depend_on_its_chunk() -> None:
    """lrfcal.stages.start.pair_score scores candidate DH sets a chunk at a time (for the cache); each candidate's
    score is
    its own: the same numbers for any chunk, and the true DH scores best among candidates around it."""
    from lrfcal.stages.start import pair_score

    rng = np.random.default_rng(3)
    dh = np.array([0.012, math.radians(80.0), 0.02, math.radians(-88.0)])
    # 40 noise-free returns (range, motor and beam angle), each a marker: eq. (3) puts them at P, and the tape's
    # distances are those between them
    lam = rng.uniform(-math.pi, math.pi, 40)
    mu = rng.uniform(-2.0, 2.0, 40)
    r = rng.uniform(0.5, 2.0, 40)
    a, al, b, be = dh
    x, y0 = a + r * np.cos(be + mu), r * np.sin(be + mu)
    y, z = y0 * math.cos(al) - b * math.sin(al), y0 * math.sin(al) + b * math.cos(al)
    P = np.stack([np.cos(lam) * x - np.sin(lam) * y, np.sin(lam) * x + np.cos(lam) * y, z], 1)
    d = np.linalg.norm(P[:, None] - P[None], axis=-1)[np.triu_indices(40, 1)]
    grid = dh + rng.normal(0.0, 1.0, (300, 4)) * np.array([0.01, 0.05, 0.01, 0.05])
    grid[17] = dh
    ref = pair_score(grid, r, lam, mu, d)
    for chunk in (2, 7, 64, 1000):  # (a one-row chunk differs in the last bits: numpy's vector loops' tail)
        np.testing.assert_array_equal(pair_score(grid, r, lam, mu, d, chunk=chunk), ref)
    assert int(np.argmax(ref)) == 17
