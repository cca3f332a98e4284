"""The calibration, as in the seed paper's Sec. III and IV-C, one stage per module.

1. markers from tape distances (mds)          5. start: mount pose from that alignment, DH from nominal
2. marker returns in the intensity image      6. Levenberg-Marquardt over the 10 parameters (solve), then
   (detection)                                   jointly with the surfaces the markers sit on (surfaces)
3. per-beam time and motor angle (timing)     7. reprojection of every beam, before and after (reproject)
4. blobs matched to markers (association)     8. tunnel planes and dimensions (geometry)

The paper's own variant (one max-intensity beam per blob, one motor angle per scan) runs beside ours as the
baseline, on the same detections and association, so that the gain is measured.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from . import association, detection, geometry, mds, observability, reproject, solve, start, surfaces, timing
from .config import DEFAULT_RANGE_SIGMA_M, CalibConfig, Check, Stopwatch, chi2_check, refuse_failed, split_in_two
from .errors import CalibrationError, InputError
from .information import information_at
from .model.kinematics import DH, PARAM_NAMES, Params, Pose
from .model.motor import MotorClock
from .model.unknowns import wrap_pi
from .targetless import calibrate_targetless, merge_returns, scene_plane_returns
from .timing import usable_scans
from .types import (
    Association,
    CalibrationResult,
    Detections,
    JointStates,
    MarkerMap,
    Nominal,
    Observations,
    Recording,
    Solution,
)


class _NoMatch(CalibrationError):
    """The blobs could not be matched to the markers (for one direction of the servo)."""


@dataclass(frozen=True)
class _Alternative:
    """One discrete alternative of the start: the servo's sign with its association and marker-only solution."""

    sign: int
    markers: MarkerMap
    assoc: Association
    matched: Observations
    start: Params
    clock: MotorClock | None
    solution: Solution
    notes: tuple[str, ...] = ()


def calibrate(
    recording: Recording, config: CalibConfig | None = None, progress: Callable[[str], None] | None = None
) -> CalibrationResult:
    """Run stages 1-8 on a recording; see the module docstring.

    ``progress(stage)`` is called with the name of each stage as it starts (for a CLI's status line).
    Raises CalibrationError (exit code 3) with the reason when the data do not support a trustworthy result,
    unless ``config.force``, which records the failed checks in the result instead.
    """
    config = config or CalibConfig()
    if config.range_sigma_m is None:  # the sensor's noise as the rig file declares it, else the UTM-30LX-EW's
        declared = recording.nominal.range_sigma_m
        config = replace(config, range_sigma_m=DEFAULT_RANGE_SIGMA_M if declared is None else declared)
    try:
        return _calibrate(recording, config, progress)
    except CalibrationError as err:
        hint = _trimmed_hint(recording, config.clock_offset_s)
        if not hint or "time span" in str(err):
            raise
        raise CalibrationError(f"{err}; {hint}") from None


#: more scans than this fraction outside the joint states' time span suggest a wrong clock offset
TRIMMED_HINT_FRACTION = 0.2


def _trimmed_hint(recording: Recording, tau0: float) -> str:
    """A hint for a refusal when many scans lie outside the joint states' time span at clock offset ``tau0``:
    the offset, the stamps or the joint states' topic is likely wrong (empty when not)."""
    if not math.isfinite(tau0):
        return ""
    joints, _ = timing.remove_spikes(recording.joints)
    covered = timing.covered_scans(recording.scans, joints, tau0)
    out = int((~covered).sum())
    if out <= TRIMMED_HINT_FRACTION * covered.size:
        return ""
    given = f" (--clock-offset {tau0:+g} s)" if tau0 != 0.0 else ""
    return (f"note: {out} of {covered.size} scans lie outside the joint states' time span at clock offset "
            f"{tau0 * 1000:+.1f} ms{given}: the clock offset (or the scan stamps) is likely wrong, which would also "
            "explain this refusal")


def _calibrate(recording: Recording, config: CalibConfig, progress: Callable[[str], None] | None) -> CalibrationResult:
    """:func:`calibrate` with ``config.range_sigma_m`` resolved."""
    if config.targetless or (config.targetless is None and recording.tape is None):
        return calibrate_targetless(recording, config, progress)
    if recording.tape is None:
        raise InputError("calibration with markers needs the tape distances (distances.csv); without markers, "
                         "calibrate targetless (--targetless)")
    clock = Stopwatch(progress, STAGES)
    notes: list[str] = []
    nominal = recording.nominal
    tau0 = config.clock_offset_s
    if not math.isfinite(tau0):
        raise InputError(f"clock offset: expected a finite number of seconds, got {tau0!r}")

    markers = mds.marker_map(recording.tape)  # 1.
    clock.lap("mds")

    scans, joints = usable_scans(recording, tau0, notes)

    detections = detection.detect(scans)  # 2.
    if not detections.blobs:
        raise CalibrationError(
            f"no marker returns found (intensity threshold {detections.threshold:.0f} counts)"
        )
    clock.lap("detection")

    returns = detection.observations(scans, joints, detections, clock_offset_s=tau0)  # 3.
    scan_lambda = timing.scan_angles(scans, joints, clock_offset_s=tau0)
    passes = timing.sweep_passes(scan_lambda)
    estimate_clock = (passes.max() >= 1) if config.estimate_clock is None else config.estimate_clock
    if not estimate_clock:
        notes.append(f"clock offset held at {tau0 * 1000:+.1f} ms (not estimated: "
                     + ("a one-way sweep does not separate it from the mount's rotation about the motor axis)"
                        if config.estimate_clock is None else "as asked)"))
    clock.lap("timing")

    # 4.-6. association and marker-only solve for each direction of the servo; the data cannot tell them apart.
    # The DH search (lrfcal.start) runs only when neither direction associates well from the nominal values.
    fit = partial(solve.solve, marker_radius_m=nominal.marker_radius_m, range_sigma_m=config.range_sigma_m,
                  beam_divergence_rad=nominal.beam_divergence_rad)
    signed = {sign: returns if sign > 0 else _replace(returns, lambda_rad=-returns.lambda_rad) for sign in (1, -1)}
    first = {sign: _associate_nominal(signed[sign], detections, markers, nominal, config) for sign in (1, -1)}
    search = not any(_good(a, signed[s], config) for s, a in first.items() if a is not None)
    clock.lap("association")  # from the nominal DH; the DH search, when needed, counts with the solve
    alternatives = []
    failures = []
    for sign in (1, -1):
        try:
            start_dh, assoc = (_associate_search(signed[sign], detections, markers, nominal, config, first[sign])
                               if search else (nominal.dh, first[sign]))
            alternatives.append(_marker_solution(sign, start_dh, assoc, markers, signed[sign], joints, nominal,
                                                 config, estimate_clock, fit))
        except CalibrationError as err:
            failures.append((sign, err))
    if not alternatives:
        raise failures[0][1]
    declared_failure = next((e for sign, e in failures if sign == 1), None)
    if declared_failure is not None and not isinstance(declared_failure, _NoMatch):
        raise declared_failure  # e.g. the layout does not determine the DH: the other direction does not help
    chosen = _choose_servo_sign(alternatives, nominal.dh, config)
    markers, assoc, matched, start, motor = chosen.markers, chosen.assoc, chosen.matched, chosen.start, chosen.clock
    ours = chosen.solution
    notes.extend(chosen.notes)
    if chosen.sign < 0:
        joints = _negated(joints)
        returns = _replace(returns, lambda_rad=-returns.lambda_rad)
    clock.lap("solve")

    surface_list, on_surfaces = [], None
    if config.surfaces:  # 6b. every beam on the markers' planes, jointly with the markers
        beam_times = scans.beam_times_s
        lambda_beams = timing.motor_angles(beam_times, joints, clock_offset_s=ours.clock_offset_s, tolerance_s=math.inf)
        surface_list, on_surfaces = surfaces.observe_surfaces(
            scans.ranges_m, scans.mu_rad, lambda_beams, detections.labels, markers.positions_W,
            nominal.marker_radius_m, ours.params, position_sigma_m=max(markers.rms_m, 0.0005),
            max_returns=config.surface_max_returns, beam_times_s=beam_times,
        )
        if len(on_surfaces):
            joint = partial(fit, matched, markers.positions_W, ours.params, model="sphere", surfaces=on_surfaces,
                            planes=surface_list, clock=motor, clock_offset_s=ours.clock_offset_s)
            ours = joint(estimate_range_bias=config.estimate_range_bias)
            if config.estimate_range_bias and not (max(ours.range_offset_sigma_m, ours.marker_range_bias_sigma_m)
                                                   <= observability.RANGE_BIAS_LIMIT_M):
                notes.append(f"range offset and marker range bias not separable by this recording (1-sigma "
                             f"{ours.range_offset_sigma_m * 1000:.3g} / {ours.marker_range_bias_sigma_m * 1000:.3g} "
                             "mm): held at 0")
                ours = joint(estimate_range_bias=False)
        elif config.estimate_range_bias:
            notes.append("range offset and marker range bias held at 0: without surface returns the markers alone "
                         "do not separate them from the marker radius and the mount")
        if config.all_planes:  # 6b generalised: every other plane of the scene too, as free planes
            others, other_planes = scene_plane_returns(scans, joints, ours, detections.labels >= 0,
                                                       list(surface_list), config)
            if len(others):
                on_surfaces = merge_returns(on_surfaces, others)
                surface_list = [*surface_list, *other_planes]
                ours = fit(matched, markers.positions_W, ours.params, model="sphere", surfaces=on_surfaces,
                           planes=surface_list, clock=motor, clock_offset_s=ours.clock_offset_s,
                           estimate_range_bias=math.isfinite(ours.range_offset_sigma_m))
                notes.append(f"{len(other_planes)} more planes of the scene ({len(others)} returns) solved jointly as "
                             "free planes")
        clock.lap("surfaces")

    checks = _checks(ours, chosen.solution, matched, markers, passes, config, fit, motor)
    refuse_failed(checks, config)

    baseline = None
    if config.baseline:  # the paper: the blob's brightest beam, the motor angle at the scan's stamp
        peaks = matched.subset(matched.is_peak)
        lambda_scan = timing.scan_angles(scans, joints, clock_offset_s=tau0)
        peaks = _replace(peaks, lambda_rad=lambda_scan[peaks.scan])
        try:
            baseline = fit(peaks, markers.positions_W, start, model="paper")
        except CalibrationError as err:
            notes.append(f"the paper's method could not be run: {err}")
        clock.lap("baseline")

    side_by_side = {"markers only": chosen.solution,
                    "markers and every plane" if config.all_planes else "markers and their surfaces": ours}
    if config.compare_targetless:  # the same recording without its markers (lrfcal.targetless), for the report
        try:
            tl = calibrate_targetless(recording, replace(config, targetless=True, force=False, geometry=False))
            side_by_side["targetless (markers ignored)"] = tl.solution
        except CalibrationError as err:
            notes.append(f"the targetless calibration of the same recording was refused: {err}")

    cloud_before, cloud_after, cloud_intensity = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    if config.clouds:  # 7.
        lambda_beams = timing.motor_angles(scans.beam_times_s, joints, clock_offset_s=ours.clock_offset_s,
                                           tolerance_s=math.inf)
        (cloud_before, cloud_after), cloud_intensity = reproject.reproject_clouds(
            scans, lambda_beams, (nominal.dh, ours.params.dh), config.cloud_stride,
            (0.0, ours.range_offset_m))
        clock.lap("reprojection")

    geometry_before = geometry_after = None
    if config.geometry and config.clouds:  # 8.
        geometry_before = geometry.tunnel_geometry(cloud_before)
        geometry_after = geometry.tunnel_geometry(cloud_after)
        clock.lap("geometry")

    return CalibrationResult(
        recording=replace(recording, scans=scans),
        markers=markers,
        detections=detections,
        observations=matched,
        association=assoc,
        start=start,
        solution=ours,
        baseline=baseline,
        cloud_before_M=cloud_before,
        cloud_after_M=cloud_after,
        cloud_intensity=cloud_intensity,
        geometry_before=geometry_before,
        geometry_after=geometry_after,
        timings_s=clock.laps,
        surfaces=tuple(surface_list),
        surface_returns=on_surfaces,
        checks=tuple(checks),
        notes=tuple(notes),
        servo_sign=chosen.sign,
        side_by_side=side_by_side,
    )


def _marker_solution(
    sign: int, start_dh: DH, assoc: Association | None, markers: MarkerMap, returns: Observations,
    joints: JointStates, nominal: Nominal, config: CalibConfig, estimate_clock: bool, fit: Callable[..., Solution],
) -> _Alternative:
    """Start, observability check and marker-only solve for one direction of the servo (``returns`` with their
    motor angles already signed), from the association made with ``start_dh``.

    Raises CalibrationError when the blobs could not be matched, when the data do not determine the DH parameters
    (judged at the start, before any solver runs), or when blobs disagree with the marker map beyond repair.
    """
    if assoc is None:
        raise _NoMatch("association: no alignment of the blobs with the marker map (check the tape "
                               "distances' file and unit, and the marker radius)")
    if sign < 0:
        joints = _negated(joints)
    if assoc.mirrored:
        markers = association.unmirror(markers)
    matched = _with_markers(returns, assoc.blob_to_marker)
    n_matched = len(np.unique(matched.marker))
    if n_matched < 4:
        raise _NoMatch(
            f"only {n_matched} markers matched to detections (need >= 4); alignment RMS {assoc.rms_m * 1000:.1f} mm"
        )
    start = Params(Pose.from_matrix(assoc.T_W_M), start_dh)  # 5.
    motor = MotorClock.from_joints(joints) if estimate_clock else None
    info, names = information_at(matched, markers.positions_W, start, model="sphere",
                                       marker_radius_m=nominal.marker_radius_m, range_sigma_m=config.range_sigma_m,
                                       clock=motor, clock_offset_s=config.clock_offset_s,
                                       beam_divergence_rad=nominal.beam_divergence_rad)
    obs = observability.analyse(info, names)
    if not obs.determined:
        raise CalibrationError(
            f"the recording does not determine {', '.join(obs.undetermined) or 'the DH parameters'} "
            f"({obs.describe()}: 1-sigma {obs.weakest_sigma_in_limits:.3g} times the limit, judged at the start): "
            f"{obs.hint()}"
        )
    sol = fit(matched, markers.positions_W, start, model="sphere", clock=motor, clock_offset_s=config.clock_offset_s)
    # blobs whose returns the fit rejects (most of them beyond 4 sigma) are matched wrongly or sit on a marker
    # that is not where the tape puts it: unassign them and solve again
    notes: list[str] = []
    for _ in range(3):  # a blob matched wrongly, or a marker that is not where the tape puts it: out, and again
        bad, why = _inconsistent_blobs(matched, sol, markers, config.range_sigma_m)
        if not bad.size:
            break
        notes.append(why)
        b2m = assoc.blob_to_marker.copy()
        b2m[bad] = -1
        assoc = Association(b2m, assoc.mirrored, assoc.T_W_M, assoc.rms_m, int((b2m >= 0).sum()))
        matched = _with_markers(returns, b2m)
        if len(np.unique(matched.marker)) < 4:
            raise CalibrationError(f"{why}; fewer than 4 markers remain")
        sol = fit(matched, markers.positions_W, sol.params, model="sphere", clock=motor,
                  clock_offset_s=sol.clock_offset_s)
    return _Alternative(sign, markers, assoc, matched, start, motor, sol, tuple(notes))


def _attempt(returns: Observations, detections: Detections, markers: MarkerMap, dh: DH, radius_m: float,
             config: CalibConfig) -> Association | None:
    """Stage 4 with the blob centres reprojected with ``dh``; None when nothing matches."""
    centres = detection.blob_centres_M(returns, dh, radius_m, n_blobs=len(detections.blobs))
    try:
        return association.associate(centres, markers, gate_m=config.association_gate_m)
    except CalibrationError:
        return None


def _associate_nominal(returns: Observations, detections: Detections, markers: MarkerMap, nominal: Nominal,
                       config: CalibConfig) -> Association | None:
    return _attempt(returns, detections, markers, nominal.dh, nominal.marker_radius_m, config)


def _good(assoc: Association, returns: Observations, config: CalibConfig) -> bool:
    """An association that leaves nothing to search for: 90 % of the blobs matched, tight alignment."""
    return assoc.n_matched >= 0.9 * len(np.unique(returns.blob)) and assoc.rms_m <= 0.25 * config.association_gate_m


def _associate_search(returns: Observations, detections: Detections, markers: MarkerMap, nominal: Nominal,
                      config: CalibConfig, from_nominal: Association | None) -> tuple[DH, Association | None]:
    """The association from the candidates of the correspondence-free DH search (lrfcal.start) or from the nominal
    DH, the best by (matched blobs, alignment RMS); returns the DH it used and the association (None: none)."""
    best_dh, best = nominal.dh, from_nominal
    for dh in start.dh_candidates(returns, len(detections.blobs), markers, nominal.dh, nominal.marker_radius_m):
        found = _attempt(returns, detections, markers, dh, nominal.marker_radius_m, config)
        if found is not None and (best is None or (found.n_matched, -found.rms_m) > (best.n_matched, -best.rms_m)):
            best_dh, best = dh, found
    return best_dh, best


def _inconsistent_blobs(matched: Observations, sol: Solution, markers: MarkerMap, range_sigma_m: float,
                        max_outlier_share: float = 0.5, floor_m: float = 0.005) -> tuple[np.ndarray, str]:
    """Blobs (indices) that disagree with the marker map, and why in words.

    First the blobs most of whose returns the solver dropped as beyond 4 sigma (matched to the wrong marker);
    else the one marker whose returns sit, on average, furthest from its tape position beyond both ``floor_m`` and
    4 sigma of that mean (sigma_r / sqrt(the number of scans seeing it)): a marker moved after taping leaves the
    tape consistent, so only its returns can tell, and their mean offset grows with every return, unlike the
    per-return test."""
    empty = np.zeros(0, dtype=np.int64)
    if sol.inlier is None:
        return empty, ""
    wrong = [int(b) for b in np.unique(matched.blob)
             if (m := matched.blob == b).sum() >= 2 and (~sol.inlier[m]).mean() > max_outlier_share]
    if wrong:
        return np.array(wrong, dtype=np.int64), f"{len(wrong)} blobs whose returns the fit rejects unassigned"
    res = np.asarray(sol.residuals_m, dtype=float)
    worst, worst_k, worst_off = 0.0, -1, 0.0
    for k in np.unique(matched.marker):
        m = (matched.marker == k) & np.all(np.isfinite(res), axis=1)
        n_scans = len(np.unique(matched.scan[m]))
        if n_scans == 0:
            continue
        offset = float(np.linalg.norm(res[m].mean(0)))
        limit = max(floor_m, 4.0 * range_sigma_m / np.sqrt(n_scans))
        if offset > limit and offset / limit > worst:
            worst, worst_k, worst_off = offset / limit, int(k), offset
    if worst_k < 0:
        return empty, ""
    blobs = np.unique(matched.blob[matched.marker == worst_k]).astype(np.int64)
    return blobs, (f"marker {markers.marker_ids[worst_k]}: its returns sit {worst_off * 1000:.0f} mm from its tape "
                   "position on average (moved after taping?): left out")


def _choose_servo_sign(alts: list[_Alternative], nominal_dh: DH, config: CalibConfig) -> _Alternative:
    """The servo's direction: the declared one (+1) unless the nominal DH contradicts it and fits the other.

    A negated motor angle together with a mirrored marker map and (alpha, b) -> (pi - alpha, -b) predicts exactly
    the same ranges (distances fix the marker map only up to a reflection), so only the nominal values can tell
    the two apart. When they contradict the declared direction, the calibration is refused with the rig-file
    setting that resolves it.
    """
    by_sign = {a.sign: a for a in alts}
    declared = by_sign.get(1)
    other = by_sign.get(-1)
    if declared is None:
        assert other is not None
        raise CalibrationError(
            "the markers match only with the servo angle negated: the servo turns the other way than declared; set "
            "servo.sign: -1 in the rig file (or --servo-sign -1) if it is mounted the other way round"
        )
    if other is None:
        return declared
    d_decl, far_decl = _nominal_distance(declared.solution.params.dh, nominal_dh, config)
    d_other, _ = _nominal_distance(other.solution.params.dh, nominal_dh, config)
    if d_decl > 1.0 and d_other <= 1.0:
        dh1, dh2 = declared.solution.params.dh, other.solution.params.dh
        raise CalibrationError(
            f"servo direction: with the declared sign (+1) the fit gives {_dh_text(dh1)}, far from the nominal "
            f"{_dh_text(nominal_dh)} ({far_decl}); with the servo angle negated it gives {_dh_text(dh2)}, which "
            "explains the data equally well. If the servo turns the other way, set servo.sign: -1 in the rig file "
            "(or --servo-sign -1)"
        )
    return declared


def _nominal_distance(dh: DH, nominal: DH, config: CalibConfig) -> tuple[float, str]:
    """max over a, alpha, b, beta of |estimate - nominal| / tolerance, and the worst parameter in words."""
    diffs = [dh.a - nominal.a, float(wrap_pi(dh.alpha - nominal.alpha)), dh.b - nominal.b,
             float(wrap_pi(dh.beta - nominal.beta))]
    ratios = [abs(d) / t for d, t in zip(diffs, config.nominal_tolerance, strict=True)]
    k = int(np.argmax(ratios))
    name = ("a", "alpha", "b", "beta")[k]
    text = (f"{name} {math.degrees(diffs[k]):+.1f} deg off" if name in ("alpha", "beta")
            else f"{name} {diffs[k] * 1000:+.1f} mm off")
    return float(ratios[k]), text


def _dh_text(dh: DH) -> str:
    return (f"a {dh.a * 1000:.1f} mm, alpha {math.degrees(dh.alpha):.2f} deg, b {dh.b * 1000:.1f} mm, "
            f"beta {math.degrees(dh.beta):.2f} deg")


def _checks(
    sol: Solution, marker_only: Solution, matched: Observations, markers: MarkerMap, passes: np.ndarray,
    config: CalibConfig, fit: Callable[..., Solution], motor: MotorClock | None,
) -> list[Check]:
    """The consistency checks a result must pass before it is written (README, stage 6c). The second opinion
    compares parts of the marker returns with the marker-only solution of them all (the same model and data
    type, so that it tests the recording's parts, not the markers against the surfaces)."""
    checks = [Check("convergence", sol.converged, sol.status.split(";")[0])]
    finite = bool(np.all(np.isfinite(sol.sigma)))
    if sol.information is not None and finite:
        obs = observability.analyse(sol.information, sol.information_names)
        checks.append(Check("observability", obs.determined,
                            f"{obs.summary()}" + ("" if obs.determined else f": {obs.hint()}")))
    else:  # a singular information (the solver's rank test): no covariance exists, so nothing is determined
        checks.append(Check("observability", False, f"the final solve is {sol.status.split(', ')[-1]}: the data do "
                            "not determine the parameters jointly (no finite covariance)"))
    checks.append(chi2_check(sol.reduced_chi2, config, "residuals", "the model does not explain the data (an "
                             "unmodelled clock offset or motion, a wrong marker radius)"))
    checks.append(_second_opinion(marker_only, matched, markers, passes, config, fit, motor))
    return checks


def _second_opinion(
    sol: Solution, matched: Observations, markers: MarkerMap, passes: np.ndarray, config: CalibConfig,
    fit: Callable[..., Solution], motor: MotorClock | None,
) -> Check:
    """Calibrate two independent parts of the data (odd and even passes of the sweep, or its two halves in time)
    and test that each agrees with the joint solution: chi2 = d^T (C_part - C_joint)^-1 d over the DH parameters
    (the part's data are a subset of the joint's), against the chi-square quantile with 4 degrees of freedom."""
    from scipy.special import chdtri  # chi-square quantile: chdtri(k, 1 - q) = ppf(q) (scipy.stats is slow to import)

    groups, how = split_in_two(matched.scan, passes)
    dh = [PARAM_NAMES.index(n) for n in ("a", "alpha", "b", "beta")]
    limit = float(chdtri(4, 1.0 - (1.0 - config.second_opinion_p / 2.0)))
    results = []
    for g in groups:
        part = matched.subset(g)
        try:
            ps = fit(part, markers.positions_W, sol.params, model="sphere", clock=None,
                     clock_offset_s=sol.clock_offset_s)
        except CalibrationError:
            return Check("second opinion", True, f"not available: {how} alone have too few returns")
        if ps.information is None or not observability.analyse(ps.information, ps.information_names).determined:
            return Check("second opinion", True, f"not available: {how} alone do not determine the DH parameters")
        d = ps.params.vector()[dh] - sol.params.vector()[dh]
        d[[1, 3]] = wrap_pi(d[[1, 3]])
        C = ps.covariance[np.ix_(dh, dh)] - sol.covariance[np.ix_(dh, dh)]
        if not (np.all(np.isfinite(C)) and np.all(np.isfinite(d))):
            return Check("second opinion", True, f"not available: {how} alone do not determine the DH parameters")
        w, V = np.linalg.eigh(0.5 * (C + C.T))
        floor = 0.05 * np.diag(ps.covariance[np.ix_(dh, dh)]).min()
        w = np.maximum(w, floor)  # the difference must not look more certain than 5 % of the part's own variance
        stat = float(d @ V @ np.diag(1.0 / w) @ V.T @ d)
        results.append((stat, d))
    worst = max(results, key=lambda r: r[0])
    ok = worst[0] <= limit
    d = worst[1]
    return Check(
        "second opinion", ok,
        f"{how} calibrated separately differ from the marker-only joint solution by chi2 {worst[0]:.3g} "
        f"(limit {limit:.3g}, 4 dof;"
        f" a {d[0] * 1000:+.2f} mm, alpha {math.degrees(d[1]):+.3f} deg, b {d[2] * 1000:+.2f} mm, "
        f"beta {math.degrees(d[3]):+.3f} deg)"
        + ("" if ok else ": the parts of the recording disagree (servo backlash or slip, an unmodelled clock "
                         "offset, markers that moved)"),
    )


def _negated(joints: JointStates) -> JointStates:
    return JointStates(stamps_s=joints.stamps_s, positions_rad=-joints.positions_rad, name=joints.name)


def _with_markers(returns: Observations, blob_to_marker: np.ndarray) -> Observations:
    """Label every return with its blob's marker and keep the labelled ones."""
    labelled = _replace(returns, marker=np.asarray(blob_to_marker)[returns.blob])
    return labelled.subset(labelled.marker >= 0)


def _replace(obs: Observations, **arrays: np.ndarray) -> Observations:
    fields = {k: getattr(obs, k) for k in obs.__dataclass_fields__}
    fields.update(arrays)
    return Observations(**fields)


#: The stages in the order they run, as reported to ``progress`` and in CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("mds", "detection", "timing", "association", "solve", "surfaces", "baseline",
                           "reprojection", "geometry")
