"""The range pattern along the scan (lrfcal.model.range_pattern): a nuisance of the targetless cost eliminated beside
the core unknowns. Its normal equations are those of the least-squares problem with the pattern's columns projected
out, exactly (H, g, the step, the core's Schur complement, the marginal sigmas and the sandwich's cluster scores,
against the dense problem built explicitly); the projection takes an injected pattern out and recovers it."""

from __future__ import annotations

import numpy as np
import pytest

from lrfcal.estimate.normal_equations import assemble, marginal_sigma, schur, scores_by_cluster, solve_step
from lrfcal.model.observations import Blocks
from lrfcal.model.range_pattern import DEGREE, basis, beam_bins, estimated_m, pattern_rows, projected
from lrfcal.model.unknowns import N_CORE

SIGMA_R = 0.005


@pytest.fixture
def problem() -> tuple[Blocks, np.ndarray, np.ndarray, np.ndarray]:
    """Random plane rows (4 planes, 300 beams in bins of 6) with a pattern, and the explicit projected Jacobian and
    residual of the same least-squares problem (core columns 0-4 and the planes' 3 nuisances each)."""
    rng = np.random.default_rng(1)
    K, P = 4000, 4
    plane = np.sort(rng.integers(0, P, K))
    pr = pattern_rows(beam_bins(rng.integers(0, 300, K)), SIGMA_R)
    Jc, Jn, r0 = rng.normal(size=(K, N_CORE)), rng.normal(size=(K, 3)), rng.normal(size=K)
    core = np.arange(5)
    b = Blocks(np.zeros(0), np.zeros((0, N_CORE)), projected(r0, pr), Jc, Jn, plane, P, pattern=pr)
    Jp = np.zeros((K, 3 * P))
    for i in range(3):
        Jp[np.arange(K), 3 * plane + i] = Jn[:, i]
    X = pr.value * pr.Z[pr.bins]
    proj = np.eye(K) - X @ np.linalg.solve(X.T @ X, X.T)
    return b, core, proj @ np.hstack([Jc[:, core], Jp]), proj @ r0


def test_normal_equations_are_the_projected_problems(problem: tuple[Blocks, np.ndarray, np.ndarray, np.ndarray]
                                                     ) -> None:
    b, core, J, r = problem
    N = assemble(b, core)
    H, g = N.dense()
    H_exp, g_exp = J.T @ J, J.T @ r
    np.testing.assert_allclose(H, H_exp, rtol=0, atol=1e-10 * np.abs(H_exp).max())
    np.testing.assert_allclose(g, g_exp, rtol=0, atol=1e-10 * np.abs(g_exp).max())
    np.testing.assert_allclose(solve_step(N, 0.0), -np.linalg.solve(H_exp, g_exp), rtol=1e-9, atol=1e-12)
    c = core.size
    S_exp = H_exp[:c, :c] - H_exp[:c, c:] @ np.linalg.solve(H_exp[c:, c:], H_exp[c:, :c])
    np.testing.assert_allclose(schur(N)[0], S_exp, rtol=0, atol=1e-10 * np.abs(S_exp).max())
    np.testing.assert_allclose(marginal_sigma(N), np.sqrt(np.diag(np.linalg.inv(H_exp))), rtol=1e-9)
    # the same rows without the pattern: more information (the pattern is not ignored)
    plain = Blocks(np.zeros(0), np.zeros((0, N_CORE)), b.r_plane, b.Jc_plane, b.Jn_plane, b.plane, b.n_planes)
    assert np.all(np.diag(assemble(plain, core).dense()[0])[:c] > np.diag(H)[:c])


def test_cluster_scores_are_the_projected_problems(problem: tuple[Blocks, np.ndarray, np.ndarray, np.ndarray]
                                                   ) -> None:
    b, core, J, r = problem
    clusters = np.random.default_rng(2).integers(0, 60, r.size)
    ids, G = scores_by_cluster(b, core, np.zeros(0, dtype=np.int64), clusters)
    G_exp = np.stack([J[clusters == c].T @ r[clusters == c] for c in ids])
    np.testing.assert_allclose(G, G_exp, rtol=0, atol=1e-10 * np.abs(G_exp).max())


def test_basis_holds_the_slow_part_and_projection_recovers_a_pattern() -> None:
    beams = np.repeat(np.arange(600), 50)
    pr = pattern_rows(beam_bins(beams), SIGMA_R)
    Z = pr.Z
    np.testing.assert_allclose(Z.T @ Z, np.eye(Z.shape[1]), atol=1e-12)
    x = np.arange(Z.shape[0], dtype=float)
    assert np.abs(Z.T @ np.vander(x, DEGREE + 1)).max() < 1e-9 * np.abs(np.vander(x, DEGREE + 1)).max()
    assert basis(np.ones(DEGREE + 1)).shape == (DEGREE + 1, 0)  # too few bins: no pattern
    # a wiggle of 1.2 mm every 61 beams plus a slow part (which the basis holds): ranges read long by p
    p_beam = 0.0012 * np.sin(2 * np.pi * np.arange(600) / 61.0) + 0.002 * (np.arange(600) / 600.0)
    res = p_beam[beams] / SIGMA_R  # (r - rep) / sigma_r with r long by p
    bins = np.arange(Z.shape[0])
    p_bin = np.array([p_beam[6 * k:6 * k + 6].mean() for k in bins])
    fast = p_bin - np.polyval(np.polyfit(x, p_bin, DEGREE), x)
    np.testing.assert_allclose(estimated_m(res, pr), fast, atol=1e-9)
    # what the cost sees: the slow part and the wiggle within a bin, not the bins' fast part
    np.testing.assert_allclose(projected(res, pr) * SIGMA_R, p_beam[beams] - fast[pr.bins], atol=1e-12)
