"""The noise a solution's residuals show (lrfcal.estimate.scatter): the range noise's correlation along the scan,
measured from neighbouring beams; the lateral means' own scatter, one residual per crossing; and the stated sigma
that follows, honest over Monte-Carlo sweeps of the synthetic rig of test_solve."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_solve import R_M, SIGMA, TRUE, _err, _markers, simulate

from lrfcal.estimate.problem import marker_problem
from lrfcal.estimate.scatter import MIN_REDUNDANT, Scatter, measured
from lrfcal.estimate.solve import solve
from lrfcal.model.kinematics import ESTIMATE_NAMES
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.noise import MAX_RHO, neighbour_correlation
from lrfcal.model.unknowns import CORE_NAMES, pack
from lrfcal.types import Observations

DH = [ESTIMATE_NAMES.index(p) for p in ("a", "alpha", "b", "beta")]


def _ar1(obs: Observations, rng: np.random.Generator, rho: float, sigma: float = SIGMA) -> np.ndarray:
    """(K,) range noise of sigma correlated along each scan as rho^|beam gap| (an AR(1) process over the beams)."""
    e = np.zeros(obs.scan.size)
    prev_scan, prev_beam, prev = -1, 0, 0.0
    for i in np.lexsort((obs.beam, obs.scan)):
        eta = rng.normal(0.0, sigma)
        if obs.scan[i] == prev_scan:
            c = rho ** float(obs.beam[i] - prev_beam)
            prev = c * prev + np.sqrt(1.0 - c * c) * eta
        else:
            prev = eta
        e[i] = prev
        prev_scan, prev_beam = int(obs.scan[i]), int(obs.beam[i])
    return e


def _kind(ss: float, count: float, share: float) -> Scatter:
    return Scatter(float("nan"), np.eye(2), ss, count, share)


def test_each_kind_is_measured_from_enough_redundant_means_alone_or_pooled() -> None:
    """A kind with MIN_REDUNDANT redundant means gets its own sum of squares over nu - 2; two kinds with fewer share
    their pooled scatter where the pool has enough, never below a kind's own; one kind with too few, alone, is left
    out (the model's sigma stands)."""
    assert MIN_REDUNDANT == 10
    alone = measured([_kind(3.0, 14.0, 2.0)])  # nu 12
    assert len(alone) == 1 and alone[0].s2 == 3.0 / 10.0
    # the V of 6 markers (layout seed 2003): 12 crossings, nu 6.6 and 9.5: 0.40 and 0.25 on their own
    across, along = _kind(1.85, 12.0, 5.36), _kind(1.88, 12.0, 2.48)
    pooled = (1.85 + 1.88) / (6.64 + 9.52 - 2.0)
    a, b = measured([across, along])
    assert a.s2 == pytest.approx(1.85 / (6.64 - 2.0)) and a.s2 > pooled  # its own: the pool would lower it
    assert b.s2 == pytest.approx(pooled) and pooled > 1.88 / (9.52 - 2.0)
    assert measured([across]) == ()  # 6.6 redundant means alone: too few
    assert measured([_kind(0.5, 4.0, 3.0), _kind(0.5, 5.0, 3.0)]) == ()  # a pool of 3: too few
    mixed = measured([_kind(3.0, 14.0, 2.0), across])  # one measured, the other alone below: left out
    assert len(mixed) == 1 and mixed[0].ss == 3.0


def test_neighbour_correlation_measures_the_scans_rho() -> None:
    """AR(1) noise of rho 0.7 along 200 scans of 100 beams: measured within 0.02 from its 19 800 neighbouring pairs;
    independent noise: 0 (clipped at 0); no neighbours: 0 from 0 pairs; a perfect correlation is held below 1."""
    rng = np.random.default_rng(0)
    scan, beam = np.repeat(np.arange(200), 100), np.tile(np.arange(100), 200)
    obs = Observations(blob=scan, marker=scan, scan=scan, beam=beam, ranges_m=np.zeros(scan.size),
                       mu_rad=np.zeros(scan.size), lambda_rad=np.zeros(scan.size), times_s=np.zeros(scan.size),
                       intensity=np.ones(scan.size), is_peak=np.zeros(scan.size, bool))
    rho, pairs = neighbour_correlation(_ar1(obs, rng, 0.7) / SIGMA, scan, beam)
    assert pairs == 200 * 99 and abs(rho - 0.7) < 0.02
    rho, _ = neighbour_correlation(rng.normal(size=scan.size), scan, beam)
    assert 0.0 <= rho < 0.03
    assert neighbour_correlation(np.ones(4), np.arange(4), np.zeros(4, np.int64)) == (0.0, 0)
    assert neighbour_correlation(np.ones(4), np.zeros(4, np.int64), np.arange(4))[0] == MAX_RHO


def test_lateral_means_are_one_residual_per_crossing() -> None:
    """The crossings' rows hold the cost's part across the scan plane exactly (its means are per crossing already),
    and at most its part along the plane (the mean of a crossing's line means, the lines' scatter about it left
    out), one row per crossing; their Jacobian is their derivative (central differences)."""
    rng = np.random.default_rng(7)
    X = _markers(rng, 12)
    obs = simulate(TRUE, X, rng, lam_step_deg=0.1)
    obs = dataclasses.replace(obs, times_s=obs.scan * 0.025)
    pb, _ = marker_problem(obs, X, MarkerSensor.of("sphere", R_M, 0.0, SIGMA))
    th, R_ref = pack(TRUE, 0.0)
    pb = pb.chosen_at(th, R_ref)
    ms = pb.markers
    assert ms is not None and ms.centring is not None
    res, J = pb.marker_rows(th, R_ref)
    assert J is not None
    across, along = ms.lateral_means(res, J)
    n, a = ms.centring[1][:, 0], ms.centring[1][:, 1]
    np.testing.assert_allclose((across[0] ** 2).sum(), ((res[:, 1:] * n).sum(1) ** 2).sum(), rtol=1e-10)
    assert (along[0] ** 2).sum() <= ((res[:, 1:] * a).sum(1) ** 2).sum() * (1 + 1e-12)
    lateral = np.ones(ms.size, bool) if ms.lateral is None else ms.lateral
    assert across[2] == along[2] == np.unique(ms.centring[0].crossing[lateral]).size > 10
    j, step = CORE_NAMES.index("alpha"), 1e-7
    dp = np.zeros(th.size)
    dp[j] = step
    plus = ms.lateral_means(pb.marker_rows(th + dp, R_ref, jac=False)[0], J)
    minus = ms.lateral_means(pb.marker_rows(th - dp, R_ref, jac=False)[0], J)
    for k in range(2):
        np.testing.assert_allclose((plus[k][0] - minus[k][0]) / (2 * step), (across, along)[k][1][:, j],
                                   rtol=1e-4, atol=1e-6)


def test_stated_sigma_is_the_spread_of_the_errors() -> None:
    """40 sweeps of 20 random markers with range noise correlated along the scan (rho 0.7): the RMS of error /
    stated sigma is within 0.75-1.3 for each DH parameter (0.85, 0.88, 0.82, 1.02 measured). The lateral means' bound
    as their sigma gave 0.74, 0.52, 0.57, 0.80: too wide, the means of lines at a regular spacing miss the centre by
    far less than the bound."""
    z = []
    for k in range(40):
        rng = np.random.default_rng(100 + k)
        X = _markers(rng, 20)
        clean = simulate(TRUE, X, rng, lam_step_deg=0.1, sigma=0.0)
        obs = dataclasses.replace(clean, times_s=clean.scan * 0.025, ranges_m=clean.ranges_m + _ar1(clean, rng, 0.7))
        sol = solve(obs, X, TRUE, sensor=MarkerSensor.of("sphere", R_M, 0.0, SIGMA))
        z.append(_err(sol.params)[DH] / sol.sigma[DH])
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.75) & (rms < 1.3)), rms
