"""What the data can determine, judged before any solver runs: the information of marker and plane returns at
given parameters (no fit), with the planes' nuisances marginalised; and the analytic Jacobian against finite
differences (a test of the observation models)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.estimate import engine
from lrfcal.estimate.engine import State
from lrfcal.estimate.normal_equations import assemble, scores_by_cluster, solve_step
from lrfcal.estimate.problem import OnPlanes, Problem, marker_set, plane_problem, plane_set
from lrfcal.estimate.scatter import correlation_excess, lateral_scatter, range_rows
from lrfcal.estimate.solve import plane_free
from lrfcal.model.kinematics import Params
from lrfcal.model.marker import MarkerModel, MarkerSensor
from lrfcal.model.motor import NO_CLOCK, Clock, MotorClock
from lrfcal.model.observations import Blocks
from lrfcal.model.unknowns import BY_NAME, CORE_NAMES, DH_SLICE, MBIAS, N_CORE, ROFF, TAU, free_by_default, pack
from lrfcal.types import Observations, SurfaceReturns

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _at(params: Params, obs: Observations, markers_W: ArrayLike, sensor: MarkerSensor, clock: Clock = NO_CLOCK
        ) -> tuple[Problem, FloatArray, FloatArray]:
    """The marker problem of ``obs`` (with ``clock.motor``: the clock offset an unknown) and the unknowns at
    ``params`` and ``clock.offset_s`` (the core vector and R_ref)."""
    ms, _ = marker_set(obs, markers_W, sensor)
    th, R_ref = pack(params, clock.offset_s)
    return Problem((ms,), sensor.range_sigma_m, clock=clock.motor), th, R_ref


def model_residuals(
    params: Params,
    obs: Observations,
    markers_W: ArrayLike,
    *,
    sensor: MarkerSensor,
) -> tuple[FloatArray, FloatArray]:
    """Whitened residuals (M,) and analytic Jacobian (M, 10) of the returns with a marker (obs.marker >= 0), the
    columns in ESTIMATE_NAMES order (the rotation as a rotation vector in frame M at w = 0).

    M = 3 K (paper) or 4 K (sphere: range residual then the 3 lateral components, per return).
    """
    pb, core, R_ref = _at(params, obs, markers_W, sensor)
    res, J = pb.marker_rows(core, R_ref)
    assert J is not None
    return res.ravel(), J.reshape(-1, N_CORE)[:, :10]


def jacobian_check(
    params: Params,
    obs: Observations,
    markers_W: ArrayLike,
    *,
    sensor: MarkerSensor,
    step: float = 1e-6,
    clock: MotorClock | None = None,
    rotation_vector: ArrayLike = (0.0, 0.0, 0.0),
    intrinsics: Mapping[str, float] | None = None,
) -> FloatArray:
    """Per column, the largest relative difference between the analytic Jacobian and central finite differences:
    every core unknown in CORE_NAMES order (lrfcal.model.unknowns), the clock offset only when ``clock`` is given
    (obs.times_s the beam times; N_CORE or N_CORE - 1 columns), evaluated at the rotation increment ``rotation_vector``
    (to test the right Jacobian away from 0) and with the ``intrinsics`` named at the values given (name -> value).

    Each column's difference is divided by max(|J_analytic| column max, 1) in whitened units. The clock column
    uses the joint velocity smoothed over ~50 ms, not the slope of the piecewise-linear interpolation, so it
    agrees with finite differences only to the interpolation's curvature error (~1e-3 relative).
    """
    pb, th, R_ref = _at(params, obs, markers_W, sensor, Clock(clock))
    th[3:6] = np.asarray(rotation_vector, dtype=float)
    for name, value in (intrinsics or {}).items():
        th[CORE_NAMES.index(name)] = value
    _, J = pb.marker_rows(th, R_ref)
    assert J is not None
    J = J.reshape(-1, N_CORE)
    cols = [j for j in range(N_CORE) if j != TAU or clock is not None]
    worst = np.zeros(len(cols))
    for out_j, j in enumerate(cols):
        dp = np.zeros(N_CORE)
        dp[j] = step
        fp = pb.marker_rows(th + dp, R_ref, jac=False)[0].ravel()
        fm = pb.marker_rows(th - dp, R_ref, jac=False)[0].ravel()
        num = (fp - fm) / (2 * step)
        scale = max(float(np.abs(J[:, j]).max()), 1.0)
        worst[out_j] = float(np.abs(num - J[:, j]).max() / scale)
    return worst


def information_at(
    obs: Observations, markers_W: ArrayLike, params: Params, *, sensor: MarkerSensor, clock: Clock = NO_CLOCK,
    surfaces: OnPlanes | None = None, sides: bool = True, estimate: Sequence[str] = (),
) -> tuple[FloatArray, tuple[str, ...]]:
    """The information J^T J (k, k) of the marker returns at ``params`` (no fit), over the core unknowns that
    would be estimated (the clock offset only with ``clock.motor``; the range offset and marker range bias only
    with ``surfaces``; and those held by default named in ``estimate``, e.g. a scale), and their names: what the
    data can determine, judged before any solver runs.

    With ``surfaces`` (with their planes, as for lrfcal.estimate.solve.solve), the surface returns' ray-plane range
    residuals and the planes' priors are added, and the planes' nuisance parameters (3 per plane) are marginalised out
    (Schur complement), evaluated at the planes the returns carry (their normals and offsets). ``sides``: only
    the lateral residuals of markers the scan plane crosses on both sides at ``params`` (as the solve does; False
    where ``params`` are a start that may be far off, e.g. with the servo's direction not yet known)."""
    pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, surfaces, sides, estimate)
    return engine.information(pb, State(th, R_ref), idx)


def _noise_free_optimum(pb: Problem, th: FloatArray, R_ref: FloatArray, idx: IntArray) -> Blocks:
    """The blocks one Gauss-Newton step from the truth ``th`` over ``idx`` (and the planes' nuisances): at the
    noise-free optimum, where what the unknowns absorb (the marker range bias of a footprint, the planes' offsets)
    is a shift of the estimate, not a scatter."""
    step = solve_step(assemble(pb.blocks(th, R_ref), idx), 0.0)
    th = th.copy()
    th[np.concatenate([idx, np.arange(N_CORE, th.size)])] += step
    return pb.blocks(th, R_ref)


def model_error_at(
    obs: Observations, markers_W: ArrayLike, params: Params, *, sensor: MarkerSensor, clock: Clock = NO_CLOCK,
    surfaces: OnPlanes | None = None, estimate: Sequence[str] = (),
) -> FloatArray:
    """The covariance (k, k) that the model's own errors add to an estimate, over the unknowns (and in the order)
    of :func:`information_at`, from returns without noise (``obs`` and ``surfaces`` of a noise-free simulation at
    the true ``params``): their range residuals are then what the model does not explain (the footprint on the
    markers and on an oblique wall, the joint states' interpolation). It is the cluster-robust (sandwich)
    covariance H^-1 (sum_c g_c g_c^T) H^-1 of those residuals, g_c the score of cluster c (a marker's crossing, a
    scan's surface returns: lrfcal.estimate.problem.Problem.clusters), at the noise-free optimum
    (:func:`_noise_free_optimum`): the part of the calibration's per-scan widening (lrfcal.estimate.solve) that
    noise does not explain. ``lrfsim plan`` adds it to the statistical covariance, as a noisy recording's sandwich
    holds both. ``estimate``: unknowns held by default that are estimated (those the data contradict,
    :func:`held_steps_at`)."""
    pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, surfaces, estimate=estimate)
    b = _noise_free_optimum(pb, th, R_ref, idx)
    H, _ = assemble(b, idx).dense()
    # a marker return's lateral residual is where its beam passes the marker's centre: noise to the model (in the
    # statistical covariance already, at the scatter its means show: :func:`lateral_scatter_at`), so only its range
    # residual is model error
    ms = pb.markers
    assert ms is not None
    r_m = b.r_dense.reshape(-1, ms.n_res).copy()
    r_m[:, 0 if ms.model == MarkerModel.PAPER else 1:] = 0.0
    b = replace(b, r_dense=r_m.ravel())
    cluster_dense, cluster_plane, _ = pb.clusters()
    G = scores_by_cluster(b, idx, cluster_dense, cluster_plane)[1]
    H_inv = scaled_pinv(H)
    k = idx.size
    sandwich = H_inv @ (G.T @ G) @ H_inv
    return 0.5 * (sandwich[:k, :k] + sandwich[:k, :k].T)


def lateral_scatter_at(
    obs: Observations, markers_W: ArrayLike, params: Params, *, sensor: MarkerSensor, clock: Clock = NO_CLOCK,
    surfaces: OnPlanes | None = None, estimate: Sequence[str] = (),
) -> FloatArray:
    """What the lateral means' own scatter changes in the covariance (k, k) over the unknowns (and in the order) of
    :func:`information_at`: H^-1 (sum over kinds (s2_kind - 1) H_kind) H^-1, each kind of mean (a crossing's across
    the scan plane, the mean of its lines' means along it) at the variance its residuals show at the noise-free
    optimum, as the calibration measures it on its own residuals (lrfcal.estimate.scatter.lateral_scatter; the
    lines' regular spacing over the disc, not the noise, makes that scatter). Usually negative: the model's sigma of
    a mean is its bound."""
    pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, surfaces, estimate=estimate)
    b = _noise_free_optimum(pb, th, R_ref, idx)
    k = idx.size
    V = scaled_pinv(assemble(b, idx).dense()[0])[:k, :k]
    middle = np.zeros((k, k))
    for s in lateral_scatter(pb, b, idx, V):
        middle += (s.s2 - 1.0) * s.H
    out = V @ middle @ V
    return 0.5 * (out + out.T)


def held_steps_at(
    obs: Observations, markers_W: ArrayLike, params: Params, names: Sequence[str], *, sensor: MarkerSensor,
    clock: Clock = NO_CLOCK, surfaces: OnPlanes | None = None, estimate: Sequence[str] = (),
) -> dict[str, float]:
    """Name -> the value each unknown of ``names`` (held by default, not in ``estimate``) steps to when freed alone
    (with its ``tested_with`` companion, lrfcal.model.unknowns) beside ``estimate``: one Gauss-Newton step from the
    truth on returns without noise, what the calibration's score test (lrfcal.estimate.covariance.held_score) steps
    to on a recording of them. Different from its start where the simulated scanner has an error the held model
    lacks (the scenario's sensor.systematic: an incidence law)."""
    out = {}
    for n in (m for m in names if m not in estimate):
        freed = [*estimate, n, *([BY_NAME[n].tested_with] if BY_NAME[n].tested_with else [])]
        pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, surfaces, estimate=freed)
        step = solve_step(assemble(pb.blocks(th, R_ref), idx), 0.0)
        i = CORE_NAMES.index(n)
        out[n] = float(th[i] + step[int(np.searchsorted(idx, i))])
    return out


def correlation_error_at(
    obs: Observations, markers_W: ArrayLike, params: Params, rho: float, *, sensor: MarkerSensor,
    clock: Clock = NO_CLOCK, surfaces: OnPlanes | None = None, estimate: Sequence[str] = (),
) -> FloatArray:
    """The covariance (k, k) that range noise correlated along the scan (neighbouring beams ``rho``, an AR(1)
    process: lrfcal.model.noise) adds to the independent-noise one (the inverse of :func:`information_at`), over the
    same unknowns in the same order: [H^-1 Delta H^-1] over the core unknowns, H the information of every unknown
    (the planes' nuisances too) and Delta the correlated range rows' excess (lrfcal.model.noise.
    correlated_range_excess) of the marker returns' range rows and the surface returns' ray-plane rows. The whole
    covariance of an estimate that weights the returns as independent is then H^-1 (H + Delta) H^-1: what its
    scatter is, and what the calibration's per-scan sandwich (lrfcal.estimate.covariance) expects. Sphere model only
    (its
    range row is the one the range noise enters)."""
    if sensor.model is not MarkerModel.SPHERE:
        raise ValueError(f"correlation_error_at: the sphere model only, got {sensor.model.value!r}")
    pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, surfaces, estimate=estimate)
    k = idx.size
    if rho == 0.0:
        return np.zeros((k, k))
    b = pb.blocks(th, R_ref)
    H, _ = assemble(b, idx).dense()
    _, u, scan, beam, _ = range_rows(pb, b, idx, scaled_pinv(H)[:, :k], k + np.arange(H.shape[0] - k))
    return correlation_excess(u, scan, beam, rho)


def turning_error_at(
    obs: Observations, markers_W: ArrayLike, params: Params, *, sensor: MarkerSensor, clock: Clock = NO_CLOCK,
) -> FloatArray:
    """The DH covariance (4, 4) the calibration adds where the sweep turns on a marker (lrfcal.stages.markers.
    _with_turning_systematic: d d^T, d the DH difference between the marker-only solve and the model variant that
    keeps only the in-plane part of those crossings' lateral residual), as expected from noise-free marker returns
    at the true ``params``: the difference of the two models' noise-free optima (one Gauss-Newton step each from
    the truth) squared, plus what noise adds to it, the variant's marker-only covariance less the whole residual's
    (the difference of two nested estimates). Zeros where no crossing turns."""
    pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, None)
    assert pb.markers is not None
    variant = pb.with_sets([replace(pb.markers, in_plane_at_turns=True)]).chosen_at(th, R_ref)
    turned = variant.markers
    if turned is None or turned.across is None or not np.any(turned.across):
        return np.zeros((4, 4))
    dh = np.searchsorted(idx, np.arange(N_CORE)[DH_SLICE])
    steps, covs = [], []
    for problem in (pb, variant):
        system = assemble(problem.blocks(th, R_ref), idx)
        steps.append(solve_step(system, 0.0)[dh])
        covs.append(scaled_pinv(system.dense()[0])[np.ix_(dh, dh)])
    d = steps[1] - steps[0]
    w, V = np.linalg.eigh(0.5 * (covs[1] - covs[0] + (covs[1] - covs[0]).T))
    return np.outer(d, d) + (V * np.clip(w, 0.0, None)) @ V.T


def map_error_at(
    info: FloatArray, obs: Observations, markers_W: ArrayLike, params: Params, map_cov: FloatArray, *,
    sensor: MarkerSensor, clock: Clock = NO_CLOCK, surfaces: OnPlanes | None = None, estimate: Sequence[str] = (),
) -> FloatArray:
    """The covariance (k, k) the marker map's own uncertainty ``map_cov`` (3n, 3n) (lrfcal.stages.mds.map_covariance)
    adds
    to an estimate, over the unknowns (and in the order) of :func:`information_at`, whose ``info`` it takes:
    G map_cov G^T with G = -info^-1 J_m^T J_c (lrfcal.estimate.problem.Problem.centre_cross), as lrfcal.estimate.solve
    adds it to a
    calibration's covariance."""
    pb, th, R_ref, idx = _problem_at(obs, markers_W, params, sensor, clock, surfaces, estimate=estimate)
    G = -scaled_pinv(info) @ pb.centre_cross(
        th, R_ref, idx, len(map_cov) // 3)
    return G @ map_cov @ G.T


def scaled_pinv(H: FloatArray) -> FloatArray:
    """The pseudo-inverse (k, k) of an information matrix H (k, k), its columns scaled to a unit diagonal first (the
    unknowns mix metres, radians and seconds)."""
    col = np.sqrt(np.maximum(np.diag(H), 1e-300))
    return np.linalg.pinv(H / np.outer(col, col), rcond=1e-12) / np.outer(col, col)


def estimated(clock: bool, surfaces: bool, estimate: Sequence[str] = ()) -> IntArray:
    """The core unknowns (indices into CORE_NAMES) a calibration estimates by default: the clock offset when the
    sweep shows it (``clock``), the range offset and the marker range bias when surface returns separate them
    (``surfaces``; lrfcal.pipeline's defaults), and those named in ``estimate``."""
    free = free_by_default(estimate=estimate)  # (which also checks the names)
    free[TAU] &= clock
    free[[ROFF, MBIAS]] &= surfaces
    free[np.isin(CORE_NAMES, estimate)] = True  # asked for, whatever the recording
    return np.flatnonzero(free).astype(np.int64)


def _problem_at(
    obs: Observations, markers_W: ArrayLike, params: Params, sensor: MarkerSensor, clock: Clock,
    surfaces: OnPlanes | None, sides: bool = True, estimate: Sequence[str] = (),
) -> tuple[Problem, FloatArray, FloatArray, IntArray]:
    """The problem of :func:`information_at` (marker rows; plane rows and priors with non-empty ``surfaces``), the
    unknowns at ``params`` (core then the planes' nuisances), R_ref, and the core unknowns estimated (indices; those
    held by default named in ``estimate`` too)."""
    pb, th, R_ref = _at(params, obs, markers_W, sensor, clock)
    if sides:  # the lateral residuals the calibration uses (lrfcal.model.marker.two_sided)
        pb = pb.chosen_at(th, R_ref)
    # the unknowns the calibration estimates: the clock offset when the sweep shows it, the range offset and
    # the marker range bias when surface returns separate them (lrfcal.pipeline's defaults)
    with_surfaces = surfaces is not None and len(surfaces) > 0
    idx = estimated(clock.motor is not None, with_surfaces, estimate)
    if surfaces is not None and with_surfaces:
        surf, nu0 = plane_set(surfaces.returns, surfaces.planes)
        return pb.with_sets([*pb.sets, surf]), np.concatenate([th, nu0]), R_ref, idx
    return pb, th, R_ref, idx


def plane_information(
    surfaces: SurfaceReturns, params: Params, *, range_sigma_m: float = 0.010, clock: MotorClock | None = None,
    clock_offset_s: float = 0.0, hold: Sequence[str] = (), estimate_range_offset: bool = False,
    dh_prior: tuple[FloatArray, FloatArray] | None = None, range_pattern: bool = False,
) -> tuple[FloatArray, tuple[str, ...]]:
    """The information (k, k) of plane returns at ``params`` (no fit) over the unknowns :func:`solve_planes`
    would estimate, the planes' nuisances (and with ``range_pattern`` the range error along the scan,
    lrfcal.model.range_pattern) marginalised, and their names: what the scene determines, judged before any solver
    runs."""
    pb, nu0 = plane_problem(surfaces, range_sigma_m, clock, dh_prior, range_pattern=range_pattern)
    th, R_ref = pack(params, clock_offset_s)
    th = np.concatenate([th, nu0])
    free = plane_free(th.size, hold, clock, estimate_range_offset)
    return engine.information(pb, State(th, R_ref), np.flatnonzero(free[:N_CORE]).astype(np.int64))


__all__ = ["correlation_error_at", "estimated", "information_at", "jacobian_check", "map_error_at", "model_error_at",
           "model_residuals", "plane_information", "scaled_pinv", "turning_error_at"]
