"""The marker map's own uncertainty: the MDS map's covariance from the tape noise (lrfcal.stages.mds.map_covariance),
how
the estimate moves with the map (lrfcal.estimate.solve.map_sensitivity) and that both join the stated covariance."""

from __future__ import annotations

import numpy as np
import pytest
from test_solve import R_M, SIGMA, TRUE, _markers, simulate

from lrfcal.estimate import covariance
from lrfcal.estimate.solve import SolveOptions, solve
from lrfcal.model.kinematics import ESTIMATE_NAMES
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.unknowns import wrap_pi
from lrfcal.stages import mds
from lrfcal.stages.surfaces import plane_prior_jacobian
from lrfcal.types import MarkerMap, TapeMeasurements


def _aligned(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """P (n, 3) moved rigidly (a reflection allowed) onto Q (n, 3) in the least-squares sense."""
    cp, cq = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - cp).T @ (Q - cq))
    return (P - cp) @ (Vt.T @ U.T).T + cq


def test_map_covariance_matches_monte_carlo() -> None:
    """150 maps from noisy tapes (1 mm): the scatter about the truth (best aligned) is what map_covariance says,
    and the map's own estimate of the tape noise is right."""
    rng = np.random.default_rng(1)
    X0 = rng.uniform(-1, 1, (10, 3)) * [1.5, 0.4, 0.6]
    ids = tuple(f"m{i}" for i in range(10))
    i, j = np.triu_indices(10, 1)
    d0 = np.linalg.norm(X0[i] - X0[j], axis=1)
    maps = [mds.marker_map(TapeMeasurements(ids, np.column_stack([i, j]), d0 + rng.normal(0, 0.001, d0.size)))
            for _ in range(150)]
    E = np.array([(_aligned(m.positions_W, X0) - X0).ravel() for m in maps])
    predicted = mds.map_covariance(X0, i, j, 0.001)
    ratio = np.diag(np.cov(E.T)) / np.diag(predicted)
    assert 0.85 < np.trace(np.cov(E.T)) / np.trace(predicted) < 1.15
    assert ratio.min() > 0.6 and ratio.max() < 1.5
    assert 0.9e-3 < np.mean([m.tape_sigma_m for m in maps]) < 1.1e-3
    assert maps[0].covariance is not None and maps[0].covariance.shape == (30, 30)


@pytest.fixture(scope="module")
def data() -> tuple:
    rng = np.random.default_rng(7)
    centres = _markers(rng, 14)
    return simulate(TRUE, centres, rng, lam_step_deg=0.1, sigma=SIGMA), centres


def _map(centres: np.ndarray, cov: np.ndarray | None) -> MarkerMap:
    return MarkerMap(tuple(f"m{k}" for k in range(len(centres))), centres, 0.0, 0.0, 0.5, False, covariance=cov)


def test_map_sensitivity_is_the_solutions_response(data: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    """Moving the markers by dc moves the solution by G dc (to first order), and the covariance gains G C G^T (the
    per-marker sandwich, which takes the larger of the two per parameter, held off: with the map's part added it binds
    on fewer parameters, here on one with the map taken as exact and none with its covariance)."""
    monkeypatch.setattr(covariance, "inflate_for_markers", lambda cov, *args, **kwargs: cov)
    obs, centres = data
    n = len(centres)
    cov_map = np.eye(3 * n) * 0.001**2
    kw = {"sensor": MarkerSensor.of("sphere", R_M, 0.0, SIGMA), "options": SolveOptions(robust=False)}
    sol = solve(obs, _map(centres, cov_map), TRUE, **kw)
    exact = solve(obs, centres, TRUE, **kw)
    assert sol.map_sensitivity is not None and sol.map_sensitivity.shape == (10, 3 * n)
    assert exact.map_sensitivity is None
    G = sol.map_sensitivity
    np.testing.assert_allclose(sol.covariance - exact.covariance, G @ cov_map @ G.T, rtol=1e-6, atol=1e-14)
    dc = np.random.default_rng(3).normal(0.0, 0.00005, (n, 3))  # small: the sphere model bends near the rim
    moved = solve(obs, centres + dc, sol.params, **kw)
    step = moved.params.vector() - sol.params.vector()
    step[[7, 9]] = wrap_pi(step[[7, 9]])
    dh = [ESTIMATE_NAMES.index(p) for p in ("a", "alpha", "b", "beta")]
    predicted = (G @ dc.ravel())[dh]
    # within 15 %: the marker returns' lateral means (lrfcal.model.coverage) leave the sphere's range rows, which bend
    # near the rim, more of the weight (10 % here at this dc, 4 % with each return's own offset; a wrong G is off by
    # its own size)
    assert np.all(np.abs(step[dh] - predicted) < 0.15 * np.abs(predicted).max() + 1e-7)
    assert np.abs(predicted).max() > 3 * np.sqrt(np.diag(exact.covariance)[dh]).min() * 0.01


def test_plane_prior_jacobian_matches_refitted_planes() -> None:
    """A marker plane's (u1, u2, offset) refitted after moving its markers changes as plane_prior_jacobian says."""
    rng = np.random.default_rng(5)
    n = 8
    X = np.column_stack([rng.uniform(0, 2, n), rng.uniform(-1, 1, n), np.full(n, 0.3)])
    X[6:] += [0.0, 0.0, 0.5]  # two markers off the plane: not members
    members = np.arange(6)

    def fit(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        c = P.mean(0)
        Vt = np.linalg.svd(P - c)[2]
        normal = Vt[2] if Vt[2][2] > 0 else -Vt[2]
        return normal, Vt[:2], c, (P - c) @ Vt[:2].T

    normal, axes, c, q = fit(X[members])
    J = plane_prior_jacobian(normal, axes, c, q, members, n)
    dX = rng.normal(0.0, 1e-6, (n, 3))
    n2, _, c2, _ = fit((X + dX)[members])
    m = n2 / (n2 @ normal)  # n + u1 axes[0] + u2 axes[1], scaled to the nuisance form
    moved = np.array([m @ axes[0], m @ axes[1], n2 @ c2 - normal @ c])
    np.testing.assert_allclose(moved, J @ dX.ravel(), rtol=1e-3, atol=1e-12)
    assert np.all(J[:, 18:] == 0.0)  # markers not on the plane do not move it


def test_errors_shared_by_a_markers_returns_widen_the_covariance() -> None:
    """The per-marker sandwich (lrfcal.estimate.covariance.inflate_for_markers): residuals that share an offset per
    marker (an
    uneven coverage of its disc) widen the covariance by about sqrt(returns per marker) for a parameter each marker
    sees alike; independent residuals leave it as it is."""
    from lrfcal.estimate.covariance import inflate_for_markers
    from lrfcal.estimate.normal_equations import Blocks

    rng = np.random.default_rng(0)
    n_markers, per = 12, 50
    marker = np.repeat(np.arange(n_markers), per)
    J = np.column_stack([np.ones(marker.size), rng.normal(size=marker.size)])  # an offset and a slope
    JtJ_inv = np.linalg.inv(J.T @ J)
    cov = JtJ_inv.copy()
    empty = np.zeros(0, dtype=np.int64)

    def widened(r: np.ndarray) -> np.ndarray:
        b = Blocks(r, J, np.zeros(0), np.zeros((0, 2)), np.zeros((0, 3)), empty, 0)
        return np.sqrt(np.diag(inflate_for_markers(cov, b, np.arange(2), marker, empty, JtJ_inv)))

    independent = widened(rng.normal(size=marker.size))
    np.testing.assert_allclose(independent, np.sqrt(np.diag(cov)), rtol=0.5)
    shared = widened(np.repeat(rng.normal(size=n_markers), per) + rng.normal(size=marker.size))
    ratio = shared[0] / np.sqrt(cov[0, 0])
    assert 0.5 * np.sqrt(per) < ratio < 2.0 * np.sqrt(per)
