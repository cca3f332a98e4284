"""Observation sets (lrfcal.model.observations) and the one estimate over them (lrfcal.estimate.engine): each set's
robust rule and choice at a new estimate, the sensor's constants, and the estimate of several sets of one kind
equal to that of their union; the per-iteration log and the status."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_solve import R_M, SIGMA, TRUE, _markers, simulate

from lrfcal.errors import InputError
from lrfcal.estimate.engine import PLANE_PASSES, State, Status, Unknowns, estimate
from lrfcal.estimate.problem import Problem, marker_set
from lrfcal.estimate.solve import solve
from lrfcal.model.kinematics import DH, Params, Pose, beam_rays_M
from lrfcal.model.marker import MarkerModel, MarkerSensor
from lrfcal.model.observations import DHPrior, ObservationSet
from lrfcal.model.plane import PlaneSet
from lrfcal.model.unknowns import CORE_NAMES, N_CORE, free_by_default, pack, plane_nuisance_start
from lrfcal.types import Observations


@pytest.fixture(scope="module")
def marker_data() -> tuple[Observations, np.ndarray]:
    rng = np.random.default_rng(11)
    X = _markers(rng, 12)
    return simulate(TRUE, X, rng, lam_step_deg=0.1), X


def test_sensor_is_one_checked_object() -> None:
    """The marker model's constants travel as one checked object, the variant an enum equal to its name."""
    s = MarkerSensor.of("sphere", 0.05, 0.004, 0.01)
    assert s.model is MarkerModel.SPHERE and s.model == "sphere" and f"{s.model}" == "sphere"
    for bad in (("bogus", 0.05, 0.0, 0.01), ("paper", -1.0, 0.0, 0.01), ("sphere", 0.05, 0.2, 0.01)):
        with pytest.raises(InputError):
            MarkerSensor.of(*bad)


def test_marker_set_keeps_and_chooses(marker_data: tuple[Observations, np.ndarray]) -> None:
    """The marker returns' robust rule leaves out a return 0.3 m long (30 sigma) and keeps the rest; chosen again at
    an estimate, the set says which lateral residuals count."""
    obs, X = marker_data
    bad = obs.ranges_m.copy()
    bad[5] += 0.3
    ms, _ = marker_set(replace(obs, ranges_m=bad), X, MarkerSensor.of("sphere", R_M, 0.0, SIGMA))
    assert isinstance(ms, ObservationSet)
    pb = Problem((ms,), SIGMA)
    th, R_ref = pack(TRUE)
    chosen = pb.chosen_at(th, R_ref)
    assert chosen.markers is not None and chosen.markers.lateral is not None
    assert chosen.markers.lateral.shape == (ms.size,)
    kept = chosen.kept(th, R_ref, (np.ones(ms.size, dtype=bool),))[0]
    assert not kept[5] and kept.sum() >= ms.size - 3


def test_solve_logs_its_iterations(marker_data: tuple[Observations, np.ndarray]) -> None:
    """solve passes through the one estimate: its Solution carries every accepted iteration (finite costs and steps,
    positive damping) and converges."""
    obs, X = marker_data
    sol = solve(obs, X, TRUE, sensor=MarkerSensor.of("sphere", R_M, 0.0, SIGMA))
    assert sol.converged and len(sol.iterations) >= 1
    assert all(np.isfinite(it.cost) and np.isfinite(it.step_sigma) and it.damping > 0 for it in sol.iterations)
    assert sol.n_iterations >= max(it.evaluations for it in sol.iterations)


def _room(rng: np.random.Generator, dh: DH) -> tuple[PlaneSet, np.ndarray]:
    """Plane returns of a nodding scanner in a 6 x 5 x 4 m box (its walls the planes, 1 cm noise), the planes
    started 1 cm and ~0.6 deg off: the set and its nuisance start."""
    lam = np.repeat(np.deg2rad(np.arange(-60.0, 60.0, 2.0)), 90)
    mu = np.tile(np.deg2rad(np.linspace(-130.0, 130.0, 90)), lam.size // 90)
    o, d = beam_rays_M(lam, mu, dh)
    normals = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]])
    offsets = np.array([3.0, 3.0, 2.5, 2.5, 2.0, 2.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (offsets[None, :] - o @ normals.T) / (d @ normals.T)
    t[~(t > 0.1)] = np.inf
    plane = np.argmin(t, axis=1)
    r = t[np.arange(lam.size), plane] + rng.normal(0.0, 0.01, lam.size)
    seen, plane = np.unique(plane, return_inverse=True)  # the walls the beams reach
    n0, t1, t2, nu0 = plane_nuisance_start(normals[seen] + rng.normal(0.0, 0.01, (seen.size, 3)), offsets[seen] + 0.01)
    n0 = n0 / np.linalg.norm(n0, axis=1, keepdims=True)
    scan = np.repeat(np.arange(lam.size // 90), 90)
    return PlaneSet(lam, mu, r, plane.astype(np.int64), n0, t1, t2, scan=scan), nu0


def _split(s: PlaneSet, nu0: np.ndarray, planes: np.ndarray) -> tuple[PlaneSet, np.ndarray]:
    """The returns of ``planes`` as a set of their own (its planes renumbered) and their nuisance start."""
    rows = np.isin(s.plane, planes)
    new = np.full(s.n_planes, -1)
    new[planes] = np.arange(planes.size)
    sub = PlaneSet(s.lam[rows], s.mu[rows], s.r[rows], new[s.plane[rows]].astype(np.int64), s.n0[planes],
                   s.t1[planes], s.t2[planes], scan=None if s.scan is None else s.scan[rows])
    return sub, nu0.reshape(-1, 3)[planes].ravel()


def test_sets_of_one_kind_estimate_as_their_union() -> None:
    """The estimate of the walls' returns as two plane sets (each with its own planes' nuisances) is that of one set
    of them all: the same DH and the same sigma (to 1e-6, the sums' order), and converged; every held unknown
    named with why."""
    rng = np.random.default_rng(3)
    dh = DH(0.02, 1.52, 0.03, 0.05)
    whole, nu0 = _room(rng, dh)
    start = Params(Pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0), DH(0.0, np.pi / 2, 0.0, 0.0))
    core, R_ref = pack(start)
    free_core = free_by_default(("x", "y", "z", "rx", "ry", "rz", "marker_range_bias", "clock_offset",
                                 "range_offset"))
    plain = replace(PLANE_PASSES, robust=False)
    results = []
    for sets, nus in (((whole,), (nu0,)),
                      tuple(zip(*(_split(whole, nu0, p) for p in (np.arange(0, whole.n_planes, 2),
                                                                  np.arange(1, whole.n_planes, 2))), strict=True))):
        pb = Problem(tuple(sets), 0.01, mount_jac=False)
        th = np.concatenate([core, *nus])
        unknowns = Unknowns.of(free_core, th.size - N_CORE, {"x": "the mount is the world frame"})
        results.append(estimate(pb, State(th, R_ref), unknowns, plain))
    one, two = results
    assert one.status is Status.CONVERGED and two.status is Status.CONVERGED
    assert len(one.log) >= 2 and one.n_evaluations >= len(one.log)
    dh_idx = [CORE_NAMES.index(n) for n in ("a", "alpha", "b", "beta")]
    truth = np.array([dh.a, dh.alpha, dh.b, dh.beta])
    sig1 = np.sqrt(np.diag(one.uncertainty.covariance))[dh_idx]
    assert np.all(np.abs(one.state.th[dh_idx] - truth) < 5 * sig1)  # the estimate itself is right
    np.testing.assert_allclose(two.state.th[dh_idx], one.state.th[dh_idx], rtol=0, atol=1e-6 * sig1.min())
    np.testing.assert_allclose(np.sqrt(np.diag(two.uncertainty.covariance))[dh_idx], sig1, rtol=1e-6)
    assert one.uncertainty.names == two.uncertainty.names
    assert one.uncertainty.held_score == {}
    assert unknowns.held["x"] == "the mount is the world frame" and unknowns.held["rx"] == "held by the call"
    assert "trusted" in unknowns.held["range_scale"]  # the model's table says why it is held by default
    assert not unknowns.free[CORE_NAMES.index("x")] and unknowns.free[N_CORE:].all()


@pytest.mark.parametrize("incidence_bias", [0.0, 0.05])
def test_stacked_sets_jacobian_matches_finite_differences(incidence_bias: float) -> None:
    """Four sets in one problem (marker returns, the DH prior, two plane sets, the second with a prior on its
    planes): each set's nuisances follow the core in the sets' order, and the stacked Jacobian is the derivative of
    the stacked residuals, column by column; with an incidence bias, its own column and the incidence's change with
    every other unknown (lrfcal.model.plane, lrfcal.model.marker)."""
    rng = np.random.default_rng(5)
    K = 80
    lam, mu = rng.uniform(-1.5, 1.5, K), rng.uniform(-2.0, 2.0, K)
    dh = DH(0.03, 1.4, 0.02, 0.3)
    o, d = beam_rays_M(lam, mu, dh)
    c = o + rng.uniform(1, 3, K)[:, None] * d + rng.normal(0, 0.05, (K, 3))
    ms, _ = marker_set(Observations(
        blob=np.arange(K) % 7, marker=np.arange(K) % 7, scan=np.arange(K), beam=np.zeros(K, np.int64),
        ranges_m=rng.uniform(1, 3, K), mu_rad=mu, lambda_rad=lam, times_s=np.zeros(K), intensity=np.ones(K),
        is_peak=np.zeros(K, bool)), c[:7], MarkerSensor.of("sphere", 0.1, 0.0, 0.01))
    sets: list[ObservationSet] = [ms, DHPrior(np.array([0.0, 1.5, 0.0, 0.2]), np.array([0.01, 0.1, 0.01, 0.1]))]
    nus = []
    for n_planes, prior in ((2, False), (3, True)):
        plane = rng.integers(0, n_planes, K).astype(np.int64)
        n0, t1, t2, nu0 = plane_nuisance_start(rng.normal(0, 1, (n_planes, 3)), rng.uniform(1, 3, n_planes))
        n0 = n0 / np.linalg.norm(n0, axis=1, keepdims=True)
        sigma = np.full(3 * n_planes, 0.05) if prior else None
        sets.append(PlaneSet(lam, mu, rng.uniform(1, 3, K), plane, n0, t1, t2, nu0 + 0.01 if prior else None,
                             sigma, scan=np.arange(K)))
        nus.append(nu0 + rng.normal(0, 0.01, nu0.size))
    pb = Problem(tuple(sets), 0.01)
    core, R_ref = pack(Params(Pose(0.1, -0.2, 0.3, 0.2, -0.1, 0.4), dh))
    core[CORE_NAMES.index("incidence_bias")] = incidence_bias
    th = np.concatenate([core, *nus])
    res, J = pb.stacked(th, R_ref)
    # prior rows: one per nuisance, 0 (residual and weight) for the planes without a prior
    assert J is not None and J.shape == (K * 4 + 4 + 2 * K + 15, N_CORE + 15)
    assert np.all(res[-15:-9] == 0.0) and np.all(J[-15:-9] == 0.0)
    assert pb.clusters()[0].size == K * 4 + 4 and pb.clusters()[1].size == 2 * K
    h = 1e-6
    for j in range(th.size):
        if j == CORE_NAMES.index("clock_offset"):
            continue  # no clock: the clock offset's column is 0 by design
        dp = np.zeros(th.size)
        dp[j] = h
        num = (pb.stacked(th + dp, R_ref, jac=False)[0] - pb.stacked(th - dp, R_ref, jac=False)[0]) / (2 * h)
        assert np.abs(num - J[:, j]).max() <= 1e-5 * max(1.0, np.abs(J[:, j]).max()), j
