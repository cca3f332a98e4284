"""The targetless speed-ups of issue 47 change no number (docs/speed.md, docs/starts.md):

- a segmentation's labels on every sampled return (lrfcal.stages.targetless.plane_returns_at) are those of the
  plain vectorised form (the beams' rays in W, the distances to every plane as one product) to the bit;
- a point's nearest neighbour among a subset it belongs to is itself (lrfcal.stages.planes.nearest_of_subset);
- the segmentation's hypothesis scores (lrfcal.stages.planes._scores, counted per chunk of points and summed once)
  are the inliers counted over all points at once, whatever the number of chunks;
- Levenberg-Marquardt with the Jacobian left out of the steps it expects to reject takes the same steps to the bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from lrfcal.config import CalibConfig
from lrfcal.estimate import normal_equations
from lrfcal.estimate.problem import plane_problem
from lrfcal.estimate.solve import pack
from lrfcal.io.recording import read_recording
from lrfcal.model.kinematics import DH, Params, beam_rays_W, points_M
from lrfcal.model.motor import MotorClock
from lrfcal.model.unknowns import N_CORE
from lrfcal.stages import holdout, planes, targetless
from lrfcal.stages.sampling import hash_sample
from lrfcal.stages.timing import usable_scans
from lrfcal.types import Iteration

CONFIG = CalibConfig(targetless=True, range_sigma_m=0.01)


@pytest.fixture(scope="module")
def sampled(shipped_recording: Callable[[str], Path]) -> tuple[targetless.Beams, np.ndarray, MotorClock, DH]:
    """room_box's sampled returns and segmentation sample as lrfcal.stages.scene.PlaneWay makes them."""
    rec = read_recording(shipped_recording("room_box"), require_distances=False)
    scans, joints = usable_scans(rec, 0.0, 0.01).value
    hold = np.broadcast_to(holdout.held_out_scans(scans.stamps_s.size)[:, None], scans.ranges_m.shape)
    beams = targetless.sample_returns(scans, CONFIG.plane_returns, skip=hold)
    seg = hash_sample(beams.scan, beams.beam, targetless.SEGMENT_SAMPLES)
    return beams, seg, MotorClock.from_joints(joints), rec.nominal.dh


def _dhs(nominal: DH) -> list[DH]:
    """The nominal and two starts far from it (other planes kept, others lost)."""
    return [nominal, DH(nominal.a + 0.02, nominal.alpha - 0.08, nominal.b - 0.03, nominal.beta + 0.1),
            DH(0.0, math.radians(60.0), 0.1, 0.0)]


def _labels_plain(beams: targetless.Beams, seg: np.ndarray, motor: MotorClock, dh: DH, tau: float,
                  thickness_m: float) -> tuple[np.ndarray, list[planes.ScenePlane]]:
    """The labelling as written before (rays from beam_rays_W, the distances to every plane as one product)."""
    lam = motor.angles(beams.times_s, tau)[0]
    P = points_M(beams.ranges_m, lam, beams.mu_rad, dh)
    seg_labels, found = planes.segment_planes(P[seg], thickness_m=thickness_m)
    if not found:
        return np.full(len(P), -1), found
    has = seg_labels >= 0
    labels = seg_labels[has][cKDTree(P[seg][has]).query(P, k=1)[1]]
    N = np.array([p.normal for p in found])
    off = np.array([p.offset_m for p in found])
    o, d = beam_rays_W(Params(targetless.MOTOR_FRAME, dh), lam, beams.mu_rad)
    n = N[labels]
    near = np.abs((P * n).sum(1) - off[labels]) <= thickness_m
    nd = (d * n).sum(1)
    facing = np.abs(nd) >= math.cos(CONFIG.max_incidence_rad)
    hit = o + ((off[labels] - (o * n).sum(1)) / np.where(np.abs(nd) > 1e-9, nd, 1e-9))[:, None] * d
    dist = np.abs(hit @ N.T - off)
    dist[np.arange(len(P)), labels] = np.inf
    return targetless._with_enough_returns(np.where(near & facing & (dist.min(1) > thickness_m), labels, -1), found)


def test_the_labels_are_those_of_the_plain_vectorised_form(sampled: tuple) -> None:
    beams, seg, motor, nominal = sampled
    for dh in _dhs(nominal):
        _, labels, found = targetless.plane_returns_at(beams, seg, motor, dh, 0.002, 0.06, CONFIG)
        ref, ref_found = _labels_plain(beams, seg, motor, dh, 0.002, 0.06)
        assert len(found) == len(ref_found)
        assert np.array_equal(labels, ref), (dh, int((labels != ref).sum()))
        assert (labels >= 0).sum() > 1000  # planes were found and labelled: the comparison tests something


def test_a_point_of_the_subset_is_its_own_nearest_neighbour() -> None:
    rng = np.random.default_rng(3)
    P = rng.normal(size=(5000, 3))
    P[4000:4010] = P[10:20]  # copies of points, in and out of the subset
    subset = np.sort(rng.choice(5000, 1500, replace=False))
    got = planes.nearest_of_subset(P, subset)
    dist_got = np.linalg.norm(P - P[subset][got], axis=1)
    dist_ref, idx_ref = cKDTree(P[subset]).query(P, k=1)
    assert np.array_equal(dist_got, dist_ref)  # the nearest, whichever of two copies
    assert np.array_equal(got[subset], np.arange(subset.size))
    same = np.all(P[subset][got] == P[subset][idx_ref], axis=1)
    assert same.all()


@pytest.mark.parametrize("n_points", [1, 255, 257, 255 * 256, 255 * 256 + 1])
def test_the_hypothesis_scores_are_the_inliers_counted_at_once(n_points: int) -> None:
    """Each hypothesis' score is the number of points within the slab whose normals agree, counted over all points
    in one product: for one chunk, a partial one, and on both sides of the 255 chunks a byte can count (the first
    hypothesis holds every point, so a count that overflowed would show)."""
    rng = np.random.default_rng(n_points)
    H = rng.normal(size=(40, 3))
    H /= np.linalg.norm(H, axis=1)[:, None]
    P = 0.3 * rng.normal(size=(n_points, 3))
    N = rng.normal(size=(n_points, 3)) + 10.0 * H[0]  # all near the first hypothesis' normal
    N /= np.linalg.norm(N, axis=1)[:, None]
    d = rng.uniform(-0.5, 0.5, 40)
    d[0] = 0.0
    thickness, cos_tol = 2.5, 0.5
    expected = ((np.abs(P @ H.T - d) <= thickness) & (np.abs(N @ H.T) >= cos_tol)).sum(0)
    got = planes._scores(P, N, H, d, thickness, cos_tol)
    assert got[0] == n_points
    np.testing.assert_array_equal(got, expected)


def test_levenberg_marquardt_without_the_jacobians_of_rejected_steps_takes_the_same_steps(sampled: tuple) -> None:
    """A solve of the DH search's kind (few returns, started far: its damping goes up and down every iteration)
    with the Jacobian computed at every step and as the engine does it: the same iterates, evaluations and log. On
    the plain hash's 8,000 returns (seed 0; the draw every start of the search used before the salt scrambled the
    hash) this solve rejects about half its steps."""
    beams, seg, motor, nominal = sampled
    start = DH(0.0, math.radians(90.0), 0.1, 0.0)
    returns, _, found = targetless.plane_returns_at(beams, hash_sample(beams.scan, beams.beam, 8000),
                                                    motor, start, 0.0, 0.04, CONFIG)
    small = returns.subset(np.arange(len(returns)) % 10 == 0)
    prior = (start.vector(), np.array([0.05, math.radians(30.0), 0.10, math.radians(30.0)]))
    pb, nu0 = plane_problem(small, 0.01, None, prior)
    th0, R = pack(Params(targetless.MOTOR_FRAME, start), 0.0)
    th0 = np.concatenate([th0, nu0])
    core = np.array([6, 7, 8, 9])
    calls: list[bool] = []

    def lazy(x: np.ndarray, jac: bool) -> normal_equations.Blocks:
        calls.append(jac)
        return pb.blocks(x, R, jac)

    runs = []
    for evaluate in (lazy, lambda x, jac: pb.blocks(x, R, True)):
        log: list[Iteration] = []
        th, n_eval, ok = normal_equations.levenberg_marquardt(th0, evaluate, core, N_CORE, huber=2.0, log=log)
        runs.append((th, n_eval, ok, log))
    (th_a, n_a, ok_a, log_a), (th_b, n_b, ok_b, log_b) = runs
    assert not all(calls), "no step was evaluated without its Jacobian: the test would test nothing"
    assert np.array_equal(th_a, th_b) and n_a == n_b and ok_a == ok_b and log_a == log_b
