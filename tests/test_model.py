"""The rig model layer (lrfcal.model): the table of unknowns, and an intrinsic added to it (the motor-angle scale)
flowing through the solver without any stage knowing its name."""

from __future__ import annotations

import numpy as np
import pytest
from test_solve import R_M, SIGMA, TRUE, _markers, simulate

from lrfcal.estimate.information import jacobian_check
from lrfcal.estimate.solve import SolveOptions, solve
from lrfcal.model.kinematics import DH, Params, Pose
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.motor import MotorClock, motor_angles
from lrfcal.model.scanner import jump_edges, reported_range, true_range
from lrfcal.model.unknowns import BY_NAME, CORE_NAMES, INTRINSICS, N_CORE, free_by_default, pack, unpack
from lrfcal.types import JointStates, Observations


def test_table_packs_and_unpacks() -> None:
    """Every unknown has a unit and a start; pack / unpack round-trip the 10 parameters; the defaults that are held
    say why."""
    assert len(CORE_NAMES) == N_CORE == len(set(CORE_NAMES))
    th, R_ref = pack(TRUE, 0.003)
    assert th.shape == (N_CORE,)
    assert th[CORE_NAMES.index("clock_offset")] == 0.003
    back = unpack(th, R_ref)
    assert np.allclose(back.vector(), TRUE.vector(), atol=1e-12)
    for name in CORE_NAMES:
        u = BY_NAME[name]
        assert u.unit in ("m", "rad", "s", "1", "m/rad") and u.meaning
        assert th[CORE_NAMES.index(name)] == u.start or u.kind in ("mount", "dh", "clock")
    free = free_by_default()
    assert all(free[CORE_NAMES.index(u)] == (not BY_NAME[u].held) for u in CORE_NAMES)
    assert not free_by_default(("a",))[CORE_NAMES.index("a")]


def test_motor_scale_is_an_intrinsic_held_at_one() -> None:
    """The motor-angle scale (a servo's gear ratio): in the table, held at 1 by default with the reason, and
    reported by a calibration as held (value 1, sigma NaN)."""
    u = BY_NAME["motor_scale"]
    assert u.kind == "intrinsic" and u.start == 1.0 and "held" in u.held
    assert "motor_scale" in INTRINSICS
    rng = np.random.default_rng(5)
    X = _markers(rng)
    obs = simulate(TRUE, X, rng)
    sol = solve(obs, X, TRUE, sensor=MarkerSensor.of("sphere", R_M, 0.0, SIGMA))
    value, sigma = sol.intrinsics["motor_scale"]
    assert value == 1.0 and np.isnan(sigma)


def test_motor_angle_scale_and_its_jacobian() -> None:
    """lambda = s q(t - tau): the scale multiplies the joint angle, and its Jacobian column (with every other) matches
    central differences through the marker model."""
    t = np.linspace(-1.0, 11.0, 1201)
    clock = MotorClock.from_joints(JointStates(t, 1.5 * np.sin(0.4 * t), "servo"))
    times = np.linspace(0.5, 9.5, 50)
    th, _ = pack(TRUE)
    k = CORE_NAMES.index("motor_scale")
    th[k] = 1.02
    m = motor_angles(th, np.zeros(50), times, clock)
    assert np.allclose(m.lam, 1.02 * clock.angles(times, 0.0)[0])
    assert dict(m.partials)[k] == pytest.approx(clock.angles(times, 0.0)[0])
    rng = np.random.default_rng(3)
    K = 200
    X = rng.uniform(-1.5, 1.5, (6, 3))
    times = rng.uniform(0.0, 10.0, K)
    obs = Observations(
        blob=np.zeros(K, np.int64), marker=rng.integers(0, 6, K), scan=np.zeros(K, np.int64),
        beam=np.zeros(K, np.int64), ranges_m=rng.uniform(0.5, 2.0, K), mu_rad=rng.uniform(-2.3, 2.3, K),
        lambda_rad=clock.angles(times, 0.0)[0], times_s=times, intensity=np.ones(K), is_peak=np.zeros(K, bool),
    )
    params = Params(Pose(0.2, -0.1, 0.5, 0.3, 0.2, 0.1), DH(0.02, 1.4, 0.05, -0.3))
    for c in (None, clock):
        err = jacobian_check(params, obs, X, sensor=MarkerSensor.of("sphere", 0.3), clock=c)
        cols = [n for n in CORE_NAMES if n != "clock_offset" or c is not None]
        assert err[cols.index("motor_scale")] < 1e-6, err
        assert err[cols.index("range_scale")] < 1e-6, err


def test_range_scale_is_estimated_when_asked() -> None:
    """The scanner reports s r_true + range_offset: the scale multiplies the predicted true range (its partial is
    r_true), true_range inverts it; a solve asked to estimate it recovers ranges 1 % long (s = 1.01) within 4 sigma
    and the DH within 4 sigma, where held at 1 the same returns put the DH far off."""
    th, _ = pack(TRUE)
    k, off = CORE_NAMES.index("range_scale"), CORE_NAMES.index("range_offset")
    th[k], th[off] = 0.99, 0.002
    r = np.array([0.5, 2.0, 7.5])
    rep = reported_range(th, r, on_marker=False)
    assert np.allclose(rep.r, 0.99 * r + 0.002) and np.array_equal(dict(rep.partials)[k], r) and rep.scale == 0.99
    assert np.allclose(true_range(th, rep.r, on_marker=False).r, r)
    rng = np.random.default_rng(11)
    X = _markers(rng)
    obs = simulate(TRUE, X, rng)
    long = Observations(**{**{f: getattr(obs, f) for f in obs.__dataclass_fields__}, "ranges_m": obs.ranges_m * 1.01})
    sensor = MarkerSensor.of("sphere", R_M, 0.0, SIGMA)
    sol = solve(long, X, TRUE, sensor=sensor, options=SolveOptions(estimate=("range_scale",)))
    value, sigma = sol.intrinsics["range_scale"]
    assert abs(value - 1.01) <= 4 * sigma and sigma < 0.002, (value, sigma)
    z = (sol.params.dh.vector() - TRUE.dh.vector()) / sol.sigma[6:]
    assert np.all(np.abs(z) <= 4), z
    held = solve(long, X, TRUE, sensor=sensor)
    assert held.intrinsics["range_scale"] == (1.0, pytest.approx(np.nan, nan_ok=True))
    assert np.max(np.abs((held.params.dh.vector() - TRUE.dh.vector()) / held.sigma[6:])) > 4


def test_jump_edges_are_the_returns_beside_a_range_jump_only() -> None:
    """The returns on either side of a near surface's edge against a far one are found (mixed pixels, veil points),
    along the scan and across it; a wall met obliquely (70-80 deg), a corner between two walls, noise below the
    floor, a missing return and its neighbours are not."""
    mu = np.radians(np.linspace(-60.0, 60.0, 121))  # 1 deg apart
    wall = 1.0 / np.cos(mu)  # a wall at x = 1 m, met at up to 60 deg
    near = wall.copy()
    near[50:71] = 0.4 / np.cos(mu[50:71])  # a box in front of it, at x = 0.4 m: edges at 49|50 and 70|71
    near[90] = np.nan  # no return
    assert np.flatnonzero(jump_edges(near[None], mu)[0]).tolist() == [49, 50, 70, 71]
    beyond = wall.copy()
    beyond[100:] = np.inf  # nothing within range (REP 117): the farthest background, its edge a jump
    assert np.flatnonzero(jump_edges(beyond[None], mu)[0]).tolist() == [99]
    # the walls of a corner (x = 1 and y = 1) meet at 45 deg: no jump; a wall along y = 0.3 met at 70-80 deg: none
    corner = np.minimum(1.0 / np.abs(np.cos(mu)), 1.0 / np.maximum(np.sin(mu), 1e-9))
    assert not jump_edges(corner[None], mu).any()
    steep = np.radians(np.linspace(10.0, 20.0, 11))
    assert not jump_edges((0.3 / np.sin(steep))[None], steep).any()
    # per-scan bearings (S, N) give the same as one row of them
    assert np.array_equal(jump_edges(np.vstack([near, wall]), np.vstack([mu, mu])),
                          jump_edges(np.vstack([near, wall]), mu))
    # across the scans: the motor turns 0.1 deg a scan and the box's edge passes between scans 2 and 3
    scans = np.vstack([wall, wall, wall, near, near])
    lam = np.radians(0.1 * np.arange(5))
    across = jump_edges(scans, mu, lam)
    assert np.flatnonzero(across[:, 60]).tolist() == [2, 3]  # the same beam on either side of the edge
    assert not jump_edges(scans, mu)[:, 60].any()  # not seen along the scan alone
    # noise: 5 mm on a wall 0.3 m away, beams 1 deg apart (5 mm of spacing: cot(10 deg) of it is 30 mm)
    rng = np.random.default_rng(0)
    noisy = (0.3 / np.cos(mu) + rng.normal(0.0, 0.005, (50, mu.size)))
    assert jump_edges(noisy, mu, np.radians(0.01 * np.arange(50))).mean() > 0.5  # noise beyond the spacing
    # beyond the floor (4 sigma of the difference) only as often as the noise goes there (6e-5 of the pairs)
    assert jump_edges(noisy, mu, np.radians(0.01 * np.arange(50)), noise_m=0.005).mean() < 1e-3
