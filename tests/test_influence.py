"""Each plane's pull on a solution (lrfcal.estimate.influence) and the check "planes agree" built on it: on a linear
least-squares problem of the planes' shape (core unknowns shared by every plane, three nuisances per plane), the pull
is the exact leave-one-plane-out change of the estimate, its covariance by the noise is the spread of that change
over noise draws, and a plane whose rows carry an error the model does not have pulls far beyond it."""

from __future__ import annotations

import numpy as np
import pytest

from lrfcal.estimate.influence import plane_pulls
from lrfcal.estimate.normal_equations import assemble
from lrfcal.model.observations import Blocks

C, P, ROWS = 3, 5, 120  # core unknowns, planes, rows per plane


def _design(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Jc (K, C), Jn (K, 3) and each row's plane (K,) of a problem with P planes of ROWS rows."""
    plane = np.repeat(np.arange(P), ROWS)
    Jc = rng.normal(size=(plane.size, C)) + 0.5 * rng.normal(size=(P, C))[plane]  # each plane its own lever
    Jn = rng.normal(size=(plane.size, 3))
    return Jc, Jn, plane


def _dense(Jc: np.ndarray, Jn: np.ndarray, plane: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The full Jacobian (rows, C + 3P) of the rows ``rows``."""
    J = np.zeros((rows.sum(), C + 3 * P))
    J[:, :C] = Jc[rows]
    idx = np.flatnonzero(rows)
    J[np.arange(idx.size)[:, None], C + 3 * plane[idx][:, None] + np.arange(3)] = Jn[rows]
    return J


def _solved(Jc: np.ndarray, Jn: np.ndarray, plane: np.ndarray, y: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The least-squares core unknowns (C,) of the residuals J x - y over the rows ``rows``."""
    return np.linalg.lstsq(_dense(Jc, Jn, plane, rows), y[rows], rcond=None)[0][:C]


def _pulls(Jc: np.ndarray, Jn: np.ndarray, plane: np.ndarray, y: np.ndarray):
    every = np.ones(plane.size, dtype=bool)
    J = _dense(Jc, Jn, plane, every)
    x = np.linalg.lstsq(J, y, rcond=None)[0]
    r = J @ x - y  # the whitened residuals at the solution, d r / d x = J
    V = np.linalg.inv(J.T @ J)[:C, :C]
    b = Blocks(np.zeros(0), np.zeros((0, C)), r, Jc, Jn, plane, P)
    pulls = plane_pulls(b, assemble(b, np.arange(C)), np.arange(C), V, 1.0, ("u", "v", "w"))
    assert pulls is not None
    return x[:C], pulls


def test_the_pull_is_the_estimate_without_the_plane() -> None:
    """Linear least squares: one Gauss-Newton step is the solution, so the pull of each plane is exactly the
    estimate without its rows minus the estimate."""
    rng = np.random.default_rng(1)
    Jc, Jn, plane = _design(rng)
    y = rng.normal(size=plane.size)
    x, pulls = _pulls(Jc, Jn, plane, y)
    assert pulls.names == ("u", "v", "w") and list(pulls.returns) == [ROWS] * P
    for j in range(P):
        without = _solved(Jc, Jn, plane, y, plane != j)
        np.testing.assert_allclose(pulls.shift[j], without - x, rtol=1e-8, atol=1e-12)


def test_the_pulls_covariance_is_their_spread_over_noise_draws() -> None:
    """Over 2000 draws of unit noise, each plane's pull scatters as its difference covariance says (variances within
    10 %, the standard error of a variance over 2000 draws about 3 %), and the chi-square of a pull averages its
    degrees of freedom."""
    rng = np.random.default_rng(2)
    Jc, Jn, plane = _design(rng)
    draws = np.array([_pulls(Jc, Jn, plane, rng.normal(size=plane.size))[1].shift for _ in range(2000)])
    pulls = _pulls(Jc, Jn, plane, rng.normal(size=plane.size))[1]
    for j in range(P):
        np.testing.assert_allclose(np.var(draws[:, j], axis=0), np.diag(pulls.difference[j]), rtol=0.1)
        chi2 = np.einsum("ni,ij,nj->n", draws[:, j], np.linalg.inv(pulls.difference[j]), draws[:, j])
        assert abs(chi2.mean() - C) < 0.2, (j, chi2.mean())


def test_a_plane_the_model_does_not_explain_pulls_beyond_the_noise() -> None:
    """A plane whose rows carry an error along the core unknowns' columns (the model has none: two surfaces taken as
    one bend the estimate so) pulls far beyond its difference covariance; the others stay within it."""
    rng = np.random.default_rng(3)
    Jc, Jn, plane = _design(rng)
    y = rng.normal(size=plane.size)
    y[plane == 2] += 2.0 * Jc[plane == 2] @ np.array([1.0, -0.5, 0.3])  # a pull no nuisance of the plane absorbs
    _, pulls = _pulls(Jc, Jn, plane, y)
    chi2 = [float(d @ np.linalg.solve(D, d)) for d, D in zip(pulls.shift, pulls.difference, strict=True)]
    assert chi2[2] > 100 and chi2[2] == pytest.approx(max(chi2))


def test_with_a_range_pattern_the_pull_holds_it_at_its_estimate() -> None:
    """Where the cost has a range pattern along the scan (lrfcal.model.range_pattern), each plane's pull is the
    estimate without its rows, the pattern held at its estimate from every plane, minus the estimate (the linear
    problem with the pattern's columns beside the core's, solved explicitly); its covariance is that of the same
    two estimates given the pattern (their difference's spread over noise draws), and a plane whose rows carry an
    error the model does not have still pulls far beyond it."""
    from lrfcal.model.range_pattern import beam_bins, pattern_rows

    rng = np.random.default_rng(4)
    Jc, Jn, plane = _design(rng)
    pr = pattern_rows(beam_bins(rng.integers(0, 120, plane.size)), 1.0)
    X = pr.value * pr.Z[pr.bins]  # the pattern's columns (K, q)
    every = np.ones(plane.size, dtype=bool)
    J = np.hstack([_dense(Jc, Jn, plane, every), X])

    def pulls_of(y: np.ndarray):
        x = np.linalg.lstsq(J, y, rcond=None)[0]
        r = J @ x - y  # orthogonal to X: the residual with the best pattern taken out
        V = np.linalg.inv(J.T @ J)[:C, :C]
        b = Blocks(np.zeros(0), np.zeros((0, C)), r, Jc, Jn, plane, P, pattern=pr)
        pulls = plane_pulls(b, assemble(b, np.arange(C)), np.arange(C), V, 1.0, ("u", "v", "w"))
        assert pulls is not None
        return x, pulls

    y = rng.normal(size=plane.size)
    x, pulls = pulls_of(y)
    given = y - X @ x[-X.shape[1]:]  # the data less the pattern estimated from every plane
    for j in range(P):
        without = _solved(Jc, Jn, plane, given, plane != j)
        np.testing.assert_allclose(pulls.shift[j], without - x[:C], rtol=1e-8, atol=1e-12)
    bad = y.copy()  # a plane the model does not explain still pulls far beyond the noise with the pattern held
    bad[plane == 2] += 2.0 * Jc[plane == 2] @ np.array([1.0, -0.5, 0.3])
    bent = pulls_of(bad)[1]
    chi2 = [float(d @ np.linalg.solve(D, d)) for d, D in zip(bent.shift, bent.difference, strict=True)]
    assert chi2[2] > 100 and chi2[2] == pytest.approx(max(chi2))
    draws = np.array([pulls_of(y_k)[1].shift for y_k in rng.normal(size=(1000, plane.size))])
    for j in range(P):  # within 15 % (measured 0.88-1.01: the pattern, estimated with the plane, takes up a share
        # of its noise)
        np.testing.assert_allclose(np.var(draws[:, j], axis=0), np.diag(pulls.difference[j]), rtol=0.15)
