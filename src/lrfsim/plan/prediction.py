"""Know before you build: the predicted 1-sigma of every calibrated parameter of a scenario, without calibrating.

The scenario's rays are cast once without noise (``lrfsim.simulation.simulate.cast_geometry(..., noise=False)``; the
mixed-pixel footprint cast as the simulator casts it, ``sensor.footprint_cast``; `lrfsim study` hands plan the cast its
trials share). Only the scans that can see a marker are cast, and every SURFACE_SCAN_STEP-th other one for the surface
returns (:func:`sparse_geometry`; all of them when those hold fewer surface returns than the calibration samples).
The marker returns are those the calibration's detection finds, each owned by the marker its ray passes with the
truth (``lrfsim.simulation.faults.marker_returns`` among ``detected_mask``), and the calibration's own observation and
noise model is evaluated at the TRUE parameters: ``lrfcal.estimate.information.information_at`` (the sphere model: range
residual
with sigma_r = the scenario sensor's range noise at the marker returns, lateral residual with sigma =
R_m sqrt(1 + k^2) / 2, k the sensor's footprint in marker radii (lrfcal.model.sphere.footprint_depth); the clock
offset is an unknown when the sweep goes both ways).
The inverse of that Fisher information is the covariance a calibration of this layout and sweep reaches (the
Cramer-Rao bound of the model), in ESTIMATE_NAMES order plus clock_offset when it is estimated. Added to it: what
the lateral means' scatter changes (``lrfcal.estimate.information.lateral_scatter_at``: each kind of mean at the
variance the noise-free residuals show, where the model's sigma is its bound; lrfcal.estimate.scatter), what
the model's own errors contribute (``lrfcal.estimate.information.model_error_at``: the per-scan sandwich of the
noise-free
returns' range residuals; negligible beside 10 mm range noise, most of the sigma of a precise scanner: issue 18,
docs/study.md "Model error"), and where the sweep turns on a marker the DH widening the calibration adds for those
crossings (``lrfcal.estimate.information.turning_error_at``).

By default the surface returns of stage 6b enter too, found as the calibration finds them
(``lrfcal.stages.surfaces.observe_surfaces`` on the noise-free cloud at the true parameters, the same subsample size):
their ray-plane range residuals and the planes' priors (from the tape noise, at least 0.5 mm as in the pipeline),
with each plane's normal and offset marginalised out. ``surfaces=False`` predicts from the marker returns alone
(stage 6). Whether the DH parameters are determined is judged as the calibration judges it before any solver
runs: from the marker returns alone (a layout the markers leave undetermined is refused even where the surfaces
would help). Range noise correlated along the scan (``sensor.noise_correlation``, an AR(1) process,
lrfcal.model.noise) adds its sandwich term (``lrfcal.estimate.information.correlation_error_at``). Not modelled: the
4-sigma
rejection. The observability verdict (``lrfcal.estimate.observability.analyse``) is the one the calibration applies
before
solving: an undetermined combination means the calibration would refuse (exit 3).
The information spans the scales the calibration holds at 1 and tests (lrfcal.stages.joint.SCALES) too: each one's
1-sigma if freed is the size of scale error the layout finds (:func:`_scale_sigmas`).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from lrfcal import (
    DEFAULT_RANGE_SIGMA_M,
    SCALES,
    CalibConfig,
    JointStates,
    Observations,
    OnPlanes,
    PlaneMarkers,
    ReturnGrid,
    Surface,
    SurfaceReturns,
    SurfaceSelection,
    analyse,
    correlation_error_at,
    estimated,
    held_steps_at,
    information_at,
    lateral_scatter_at,
    map_covariance,
    map_error_at,
    mirror_check,
    model_error_at,
    most_contradicted,
    observe_surfaces,
    of_covariance,
    scaled_pinv,
    turning_error_at,
)
from lrfcal.errors import CalibrationError
from lrfcal.model.kinematics import DH, DH_NAMES, ESTIMATE_NAMES, Params
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.motor import Clock, MotorClock, dequantised
from lrfcal.model.unknowns import BY_NAME, CORE_NAMES
from lrfsim.scenario.file import Scenario, require_markers

from .result import SOURCE_MARKERS, SOURCE_SURFACES, Plan, ToleranceCheck, format_value
from .sparse_cast import NOT_SAMPLED, SURFACE_SCAN_STEP, sparse_geometry

if TYPE_CHECKING:
    from lrfsim.simulation.simulate import Geometry

FloatArray = NDArray[np.float64]

#: the DH block of the covariance (ESTIMATE_NAMES order)
DH_ROWS = np.ix_(*[[ESTIMATE_NAMES.index(n) for n in DH_NAMES]] * 2)
def marker_observations(scenario: Scenario, geometry: Geometry | None = None
                        ) -> tuple[Observations, FloatArray, Params, MotorClock, float, Any]:
    """Cast the scenario's rays once without noise and return the marker returns as the calibration sees them.
    ``geometry``: the scenario's cast made before (lrfsim.simulation.simulate.cast_geometry, as `lrfsim study` shares it
    with its trials, or :func:`sparse_geometry`), read without noise instead of casting (the same sigmas to 1e-11 on the
    shipped scenarios).

    Returns (observations with the true marker of each return and the true motor angles, marker centres (n, 3) in
    W, the true Params, the servo's MotorClock (reported joint states), the true clock offset [s], the SimResult).
    """
    from lrfsim.simulation.faults import detected_mask, marker_returns
    from lrfsim.simulation.simulate import cast_geometry, simulate_from_geometry

    if geometry is None:
        geometry = cast_geometry(scenario, noise=False)
    result = simulate_from_geometry(scenario, geometry, noise=False)
    owner = marker_returns(result, scenario, among=detected_mask(result, scenario))
    s_idx, b_idx = np.nonzero(owner >= 0)
    sensor = scenario.sensor
    times = result.scan_stamps_s[s_idx] + b_idx * sensor.time_increment_s
    K = s_idx.size
    obs = Observations(
        blob=np.zeros(K, dtype=np.int64), marker=owner[s_idx, b_idx].astype(np.int64), scan=s_idx.astype(np.int64),
        beam=b_idx.astype(np.int64), ranges_m=result.ranges_m[s_idx, b_idx], mu_rad=result.mu_rad[b_idx],
        lambda_rad=result.beam_lambda_rad[s_idx, b_idx], times_s=times, intensity=result.intensities[s_idx, b_idx],
        is_peak=np.zeros(K, dtype=bool),
    )
    # the joint states as the calibration interpolates them (lrfcal.stages.timing.usable_scans: quantisation taken out)
    joints = JointStates(stamps_s=result.joints.stamps_s,
                         positions_rad=dequantised(result.joints.stamps_s, result.joints.positions_rad))
    params = Params(result.truth.mount, result.truth.dh)
    return obs, result.truth.markers_W, params, MotorClock.from_joints(joints), result.truth.clock_offset_s, result


def expected_map_covariance(scenario: Scenario, markers_W: FloatArray) -> FloatArray:
    """The covariance (3n, 3n) of the marker map the calibration will build from this scenario's tape: every pair
    measured with the tape's sigma, a fraction f of them as f times the information (lrfcal.stages.mds.map_covariance;
    in the plane of a coplanar layout)."""
    from lrfsim.sensors.tape import affine_dimension

    i, j = np.triu_indices(len(markers_W), 1)
    sigma = scenario.tape.sigma_m / math.sqrt(max(scenario.tape.pair_fraction, 1e-9))
    X = np.asarray(markers_W, dtype=float)
    if affine_dimension(X) == 3:
        return map_covariance(X, i, j, sigma)
    Vt = np.linalg.svd(X - X.mean(0))[2]  # the layout's plane is z = 0 in the frame of its principal axes
    R = np.kron(np.eye(len(X)), Vt.T)
    return R @ map_covariance((X - X.mean(0)) @ Vt.T, i, j, sigma, planar=True) @ R.T


def scenario_range_sigma(scenario: Scenario, ranges_m: FloatArray) -> float:
    """The range noise of the scenario's sensor at the marker returns (the median over ``ranges_m`` of the noise
    band's sigma, times faults.range_noise_scale); the calibration's 10 mm (CalibConfig) for a noise-free sensor.
    For the UTM-30LX-EW of the shipped scenarios both are 10 mm below 10 m."""
    from lrfsim.sensors.lidar import typical_range_sigma
    from lrfsim.simulation.faults import scale_range_noise

    sigma = typical_range_sigma(ranges_m, scale_range_noise(scenario).sensor)
    return DEFAULT_RANGE_SIGMA_M if sigma is None else sigma


def plan(scenario: Scenario, *, range_sigma_m: float | None = None, surfaces: bool = True,
         geometry: Geometry | None = None) -> Plan:
    """Predict the 1-sigma of every calibrated parameter of ``scenario`` from the Fisher information of its
    noise-free geometry (module docstring). ``range_sigma_m`` defaults to the scenario's sensor noise at the marker
    returns (:func:`scenario_range_sigma`);
    ``surfaces`` adds the surface returns of stage 6b (as the calibration does by default); ``geometry``: the
    scenario's cast, when the caller has made it (:func:`marker_observations`).

    Raises:
        InputError: a marker-less scenario.
        CalibrationError: fewer than 4 marker returns on fewer than 3 markers (nothing to predict from).
    """
    require_markers(scenario, "lrfsim plan", "predicts from the marker returns")
    t0 = time.perf_counter()
    tol = scenario.rig.nominal_dh_tolerance  # the rig file's dh_tolerance, as the calibration reads it
    config = CalibConfig(dh_tolerance=None if tol is None else (tol.a, tol.alpha, tol.b, tol.beta))
    cast = sparse_geometry(scenario) if geometry is None else geometry
    obs, markers_W, params, motor, tau, result = marker_observations(scenario, cast)
    sigma_r = scenario_range_sigma(scenario, obs.ranges_m) if range_sigma_m is None else float(range_sigma_m)
    n_seen = int(np.unique(obs.marker).size)
    if len(obs) < 4 or n_seen < 3:
        raise CalibrationError(f"plan {scenario.name}: {len(obs)} marker returns on {n_seen} markers seen by the "
                               "sweep; a calibration needs >= 4 returns on >= 3 markers")
    two_way = scenario.servo.passes >= 2
    assert scenario.markers is not None  # require_markers above
    radius = float(scenario.markers.radius_m)
    on_planes, planes, source = None, None, SOURCE_MARKERS
    if surfaces and config.surfaces:
        sample = SURFACE_SCAN_STEP if cast.scans_cast is not None else 1  # sparse_geometry's cast: a sample
        planes, on_planes = _surface_returns(scenario, result, obs, markers_W, params, config, sample)
        if sample > 1 and planes and len(on_planes) < config.surface_max_returns:  # fewer than the calibration
            cast = sparse_geometry(scenario, rest_of=cast)  # samples: all of them, every scan cast
            obs, markers_W, params, motor, tau, result = marker_observations(scenario, cast)
            planes, on_planes = _surface_returns(scenario, result, obs, markers_W, params, config)
        if len(on_planes):
            source = SOURCE_SURFACES
        else:
            on_planes = planes = None
    sensor = MarkerSensor.of("sphere", radius, float(scenario.sensor.divergence_rad), sigma_r)
    ev = _Evidence(obs, markers_W, params, sensor, Clock(motor if two_way else None, tau),
                   None if on_planes is None else OnPlanes(on_planes, planes))
    info_markers, names = information_at(obs, markers_W, params, sensor=sensor, clock=ev.clock)
    # over the held scales too (each with its companion): their sigmas below; the estimate's is the submatrix
    freed = sorted({*SCALES, *(BY_NAME[n].tested_with for n in SCALES)} - {""})
    wide, wide_names = information_at(obs, markers_W, params, sensor=sensor, clock=ev.clock, surfaces=ev.surfaces,
                                      estimate=freed)
    wide = 0.5 * (wide + wide.T)
    notes: list[str] = []
    freed, base, scale_sigma = _contradicted(ev, wide, wide_names, two_way, notes)
    info = wide[np.ix_(*[[wide_names.index(n) for n in base]] * 2)]
    cov, model_sigma, map_sigma = _covariance(scenario, info, names, ev, notes, freed)
    sigma = {n: float(math.sqrt(max(cov[i, i], 0.0))) for i, n in enumerate(names)}
    # the verdict the calibration gives before solving: from the marker returns alone (lrfcal.pipeline)
    obsv = analyse(0.5 * (info_markers + info_markers.T), names, params.dh.alpha)
    if not obsv.determined:
        for i, n in enumerate(DH_NAMES):  # the DH verdict: an undetermined parameter has no useful sigma
            if not math.isfinite(obsv.sigma[i]):
                sigma[n] = math.inf
    if not obsv.determined and on_planes is not None:
        notes.append("the sigmas include the surface returns, but the calibration judges the marker returns alone "
                     "before solving: it would refuse this recording")
    if not two_way:
        notes.append("one-way sweep (or spin): the clock offset is held (the calibration cannot separate it from rz)")
    assert tuple(names[:10]) == ESTIMATE_NAMES
    return Plan(scenario=scenario.name, names=names, covariance=cov, sigma=sigma, observability=obsv,
                tolerances=_tolerance_checks(scenario, names, sigma, cov), n_returns=len(obs), n_markers_seen=n_seen,
                n_markers=int(len(markers_W)), clock_estimated=two_way, range_sigma_m=sigma_r,
                seconds=time.perf_counter() - t0, information_source=source,
                n_surface_returns=0 if on_planes is None else len(on_planes), notes=tuple(notes),
                observability_solved=of_covariance(cov, names, params.dh.alpha),  # calibrate's final check's rule
                model_sigma=model_sigma,
                map_sigma=map_sigma, scale_sigma=scale_sigma,
                range_correlation=float(scenario.sensor.noise_correlation),
                mirror=_mirror(params.dh, scenario, config, np.array([sigma[n] for n in DH_NAMES])),
                covariance_names=base if len(base) == cov.shape[0] else names)


def _mirror(truth: DH, scenario: Scenario, config: CalibConfig, dh_sigma: FloatArray) -> tuple[bool, str]:
    """Whether the calibration's mirror check passes for an estimate at the truth with the predicted ``dh_sigma`` (4,)
    and the scenario's nominal DH (lrfcal.estimate.checks.mirror_check: the same rule), and its words."""
    c = mirror_check(truth, scenario.rig.nominal_dh.to_dh(), config, dh_sigma)
    return c.passed, c.detail


def _contradicted(ev: _Evidence, wide: FloatArray, wide_names: tuple[str, ...], two_way: bool, notes: list[str]
                  ) -> tuple[tuple[str, ...], tuple[str, ...], dict[str, float]]:
    """The held intrinsics the calibration would free on a recording of this scenario: where the noise-free returns
    step one beyond SCALE_Z_LIMIT of its sigma (lrfcal.stages.joint.most_contradicted, the calibration's rule;
    lrfcal.estimate.information.held_steps_at), one at a time as the calibration frees them (the scenario's
    sensor.systematic: an incidence law the held model lacks). With them: the unknowns estimated and the sigmas of
    those still held (:func:`_scale_sigmas`)."""
    at = (ev.obs, ev.markers_W, ev.params)
    freed: tuple[str, ...] = ()
    while True:
        base = tuple(CORE_NAMES[i] for i in estimated(two_way, ev.surfaces is not None, freed))
        sigma = _scale_sigmas(wide, wide_names, base, freed)
        steps = held_steps_at(*at, tuple(sigma), sensor=ev.sensor, clock=ev.clock, surfaces=ev.surfaces,
                              estimate=freed)
        name = most_contradicted({n: (steps[n], sigma[n]) for n in steps})
        if name is None:
            return freed, base, sigma
        freed = (*freed, name)
        notes.append(f"{name} estimated, as the calibration would: the recording's returns step it to "
                     f"{steps[name]:.4g}, {abs(steps[name] - BY_NAME[name].start) / sigma[name]:.0f} sigma from "
                     f"{BY_NAME[name].start:g} (the scenario's scanner has an error the held model lacks)")


def _scale_sigmas(wide: FloatArray, wide_names: tuple[str, ...], names: tuple[str, ...],
                  freed: tuple[str, ...] = ()) -> dict[str, float]:
    """Scale name -> the statistical 1-sigma it would have if freed beside ``names`` (with the unknown its score
    test frees beside it, lrfcal.model.unknowns ``tested_with``), from the information ``wide`` over ``wide_names``:
    the size of scale error the calibration's score test finds (SCALE_Z_LIMIT of it; at least, since where the plain
    score steps beyond 2 sigma the calibration widens that sigma for the model error, lrfcal.estimate.covariance)."""
    out = {}
    for n in (m for m in SCALES if m not in freed):
        sub = [*names, *dict.fromkeys(m for m in (n, BY_NAME[n].tested_with) if m and m not in names)]
        k = [wide_names.index(m) for m in sub]
        var = scaled_pinv(wide[np.ix_(k, k)])[sub.index(n), sub.index(n)]
        out[n] = float(math.sqrt(var)) if var > 0 else math.inf
    return out


@dataclass(frozen=True)
class _Evidence:
    """What a plan predicts from: the noise-free marker returns ``obs`` on the markers ``markers_W`` (n, 3) at the
    true ``params``, the marker sensor, the clock, and the surface returns on their planes (None: markers only)."""

    obs: Observations
    markers_W: FloatArray
    params: Params
    sensor: MarkerSensor
    clock: Clock
    surfaces: OnPlanes | None


def _covariance(scenario: Scenario, info: FloatArray, names: tuple[str, ...], ev: _Evidence, notes: list[str],
                freed: tuple[str, ...] = ()) -> tuple[FloatArray, dict[str, float], dict[str, float]]:
    """The predicted covariance from the information ``info`` over ``names`` (column-scaled inversion: the
    parameters mix metres, radians and seconds), with the model error and the marker map's part added, and those
    two parts' sigmas by name; infinite where the information is singular (said in ``notes``)."""
    col = np.sqrt(np.maximum(np.diag(info), 1e-300))
    scaled = info / np.outer(col, col)
    sv = np.linalg.svd(scaled, compute_uv=False)
    if sv[-1] <= sv[0] * 1e-12:
        notes.append(f"information singular (condition {sv[0] / max(sv[-1], 1e-300):.2e})")
        return np.full(info.shape, np.inf), {}, {}
    # the statistical covariance, plus what the model's own errors add (the residuals of the noise-free returns at
    # the truth: lrfcal.estimate.information.model_error_at), as the calibration's per-scan widening holds both
    at = (ev.obs, ev.markers_W, ev.params)
    model_cov = model_error_at(*at, sensor=ev.sensor, clock=ev.clock, surfaces=ev.surfaces, estimate=freed)
    # the lateral means at the scatter their regular spacing gives them, as the calibration measures it on its own
    # residuals (lrfcal.estimate.scatter)
    scatter_cov = lateral_scatter_at(*at, sensor=ev.sensor, clock=ev.clock, surfaces=ev.surfaces, estimate=freed)
    rho = float(scenario.sensor.noise_correlation)  # range noise correlated along the scan: its sandwich term
    corr_cov = correlation_error_at(*at, rho, sensor=ev.sensor, clock=ev.clock, surfaces=ev.surfaces, estimate=freed)
    # and what the tape's noise adds through the marker map (the calibration's covariance holds it too)
    tape_cov = map_error_at(info, *at, expected_map_covariance(scenario, ev.markers_W), sensor=ev.sensor,
                            clock=ev.clock, surfaces=ev.surfaces, estimate=freed)
    # where the sweep turns on a marker, the model error the calibration adds for it too (DH only)
    turn_cov = turning_error_at(*at, sensor=ev.sensor, clock=ev.clock)
    model_cov[DH_ROWS] += turn_cov
    if np.any(turn_cov):
        notes.append("crossings of the sweep turn on some markers: the DH sigmas include the model error the "
                     "calibration adds for them (" + ", ".join(
                         f"{n} {format_value(n, math.sqrt(turn_cov[i, i]))}" for i, n in enumerate(DH_NAMES)) + ")")

    def sigmas(c: FloatArray) -> dict[str, float]:
        return {n: float(math.sqrt(max(c[i, i], 0.0))) for i, n in enumerate(names)}

    stat = np.linalg.inv(scaled) / np.outer(col, col) + scatter_cov + corr_cov
    return stat + model_cov + tape_cov, sigmas(model_cov), sigmas(tape_cov)


def _tolerance_checks(scenario: Scenario, names: tuple[str, ...], sigma: dict[str, float], cov: FloatArray
                      ) -> tuple[ToleranceCheck, ...]:
    """Each of the scenario's tolerances against the predicted sigma (the position's and rotation's: the root of
    the trace of their blocks)."""
    tol = scenario.tolerances

    def block(keys: tuple[str, ...]) -> float:
        i = [names.index(n) for n in keys]
        return float(math.sqrt(max(np.trace(cov[np.ix_(i, i)]), 0.0)))

    return (
        ToleranceCheck("a", tol.a_m, sigma["a"]),
        ToleranceCheck("alpha", tol.alpha_rad, sigma["alpha"]),
        ToleranceCheck("b", tol.b_m, sigma["b"]),
        ToleranceCheck("beta", tol.beta_rad, sigma["beta"]),
        ToleranceCheck("position", tol.position_m, block(("x", "y", "z"))),
        ToleranceCheck("rotation", tol.rotation_rad, block(("rx", "ry", "rz"))),
    )


def _surface_returns(scenario: Scenario, result: Any, obs: Observations, markers_W: FloatArray, params: Params,
                     config: CalibConfig, step: int = 1) -> tuple[list[Surface], SurfaceReturns]:
    """The marker-carrying planes and their returns in the noise-free recording, found as the pipeline finds them
    (labels: the marker returns; position sigma of the markers: the tape's, at least 0.5 mm), from every
    ``step``-th scan (an even sample of the sweep: the sparse cast casts more scans near the markers)."""
    S, N = result.ranges_m.shape
    labels = np.full((S, N), -1, dtype=np.int64)
    labels[obs.scan, obs.beam] = obs.marker
    labels[np.arange(S) % step != 0] = NOT_SAMPLED
    beam_times = result.scan_stamps_s[:, None] + np.arange(N)[None, :] * scenario.sensor.time_increment_s
    grid = ReturnGrid(result.ranges_m, result.mu_rad, result.beam_lambda_rad, labels, beam_times)
    on_markers = PlaneMarkers(markers_W, float(scenario.marker_radius_m or 0.0), max(scenario.tape.sigma_m, 0.0005))
    return observe_surfaces(grid, on_markers, params, selection=SurfaceSelection(config.surface_max_returns))


__all__ = ["marker_observations", "plan", "scenario_range_sigma"]
