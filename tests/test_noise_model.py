"""The range noise's correlation along the scan (lrfcal.model.noise): the pairs it couples and the sandwich term of
a least-squares estimate that weights correlated returns as independent."""

from __future__ import annotations

import numpy as np
import pytest

from lrfcal.model.noise import correlated_pairs, correlated_range_excess
from lrfsim.sensors.lidar import correlated_along_beams


def _returns(rng: np.random.Generator, S: int, N: int, K: int) -> tuple[np.ndarray, np.ndarray]:
    """K distinct (scan, beam) returns out of an S x N grid, unordered."""
    flat = rng.choice(S * N, size=K, replace=False)
    return (flat // N).astype(np.int64), (flat % N).astype(np.int64)


def test_excess_is_the_dense_correlation_matrix_less_the_identity() -> None:
    """Delta = U^T (C - I) U with C_ij = rho^|beam_i - beam_j| in the same scan, 0 across scans."""
    rng = np.random.default_rng(3)
    scan, beam = _returns(rng, 6, 60, 150)
    U = rng.standard_normal((150, 5))
    rho = 0.7
    same = scan[:, None] == scan[None, :]
    C = np.where(same, rho ** np.abs(beam[:, None] - beam[None, :]).astype(float), 0.0)
    np.testing.assert_allclose(correlated_range_excess(U, scan, beam, rho), U.T @ (C - np.eye(150)) @ U,
                               atol=1e-4 * np.abs(U.T @ U).max())
    i, j, w = correlated_pairs(scan, beam, rho)
    assert np.all(scan[i] == scan[j]) and np.all(i != j) and np.all(w > 0)
    assert len(set(zip(np.minimum(i, j), np.maximum(i, j), strict=True))) == i.size  # each pair once
    assert correlated_pairs(scan, beam, 0.0)[0].size == 0
    with pytest.raises(ValueError, match="correlation"):
        correlated_pairs(scan, beam, 1.0)


def test_sandwich_matches_the_scatter_of_a_least_squares_fit_with_ar1_noise() -> None:
    """A linear least-squares fit of rows on some beams of S scans, with range noise drawn as lrfsim draws it
    (lrfsim.sensors.lidar.correlated_along_beams, rho 0.7): the scatter of its estimate is H^-1 (H + Delta) H^-1 (within
    the Monte-Carlo's own 1/sqrt(2 n) of each sigma, 4 of them), about twice the independent-noise H^-1."""
    rng = np.random.default_rng(11)
    S, N, rho, n = 20, 100, 0.7, 2000
    scan, beam = _returns(rng, S, N, 1500)
    t = beam / N
    U = np.stack([np.ones_like(t), t, np.cos(3 * t + scan), np.sin(5 * t)], 1)  # smooth along the beams
    H = U.T @ U
    H_inv = np.linalg.inv(H)
    predicted = np.sqrt(np.diag(H_inv @ (H + correlated_range_excess(U, scan, beam, rho)) @ H_inv))
    noise = correlated_along_beams(rng.standard_normal((n, S, N)).reshape(n * S, N), rho).reshape(n, S, N)
    estimates = (H_inv @ U.T @ noise[:, scan, beam].T).T  # (n, 4)
    measured = estimates.std(0)
    assert np.all(np.abs(measured / predicted - 1) < 4 / np.sqrt(2 * n)), (measured, predicted)
    assert np.all(predicted > 1.5 * np.sqrt(np.diag(H_inv)))  # the correlation's cost is not small here
