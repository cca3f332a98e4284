"""Calibration with markers: the seed paper's Sec. III and IV-C as observation sets and a start.

1. markers from tape distances (mds)          5. start: mount pose from that alignment, DH from nominal
2. marker returns in the intensity image      6. the marker returns solved for each direction of the servo
   (detection)                                   (solve), the direction chosen (lrfcal.checks.servo_direction);
3. per-beam time and motor angle (timing)        then jointly with the surfaces the markers sit on (surfaces),
4. blobs matched to markers (association)        and with every other plane of the scene when asked

The paper's own variant (one max-intensity beam per blob, one motor angle per scan) runs beside ours as the
baseline, on the same detections and association, so that the gain is measured. lrfcal.pipeline runs this and
the shared stages (checks, reprojection, geometry).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from . import association, detection, mds, minima, observability, solve, start, surfaces, timing
from .checks import dh_text, far_from_nominal, marker_checks, mirror_check, nearer_mirror, servo_direction
from .config import CalibConfig, Stopwatch
from .errors import CalibrationError
from .information import information_at
from .model.kinematics import DH, Params, Pose, dh_twins, homogeneous
from .model.marker import crossings
from .model.motor import MotorClock
from .model.unknowns import dh_difference, pack
from .problem import marker_problem
from .targetless import merge_returns, scene_plane_returns
from .types import (
    Association,
    CalibrationResult,
    Detections,
    JointStates,
    MarkerMap,
    Nominal,
    Observations,
    Recording,
    Scans,
    Solution,
)


class _NoMatch(CalibrationError):
    """The blobs could not be matched to the markers (for one direction of the servo)."""


@dataclass(frozen=True)
class Alternative:
    """One discrete alternative of the start: the servo's sign with its association and marker-only solution."""

    sign: int
    markers: MarkerMap
    assoc: Association
    matched: Observations
    start: Params
    clock: MotorClock | None
    solution: Solution
    notes: tuple[str, ...] = ()
    estimate: tuple[str, ...] = ()  # the unknowns held by default that its solves estimate (SCALES found off)


def fit_markers(recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch,
                notes: list[str]) -> CalibrationResult:
    """Stages 1-6 (module docstring) on ``recording`` (its scans those the joint states cover) and their checks: a
    result without clouds (lrfcal.pipeline adds them).

    Raises:
        CalibrationError: no marker returns, no match, or the layout does not determine the DH parameters.
    """
    scans, nominal, tau0 = recording.scans, recording.nominal, config.clock_offset_s
    assert recording.tape is not None
    markers = mds.marker_map(recording.tape)  # 1.
    clock.lap("mds")
    detections = detection.detect(scans)  # 2.
    if not detections.blobs:
        raise CalibrationError(f"no marker returns found (intensity threshold {detections.threshold:.0f} counts)")
    clock.lap("detection")
    returns = detection.observations(scans, joints, detections, clock_offset_s=tau0)  # 3.
    passes = timing.sweep_passes(timing.scan_angles(scans, joints, clock_offset_s=tau0))
    estimate_clock = (passes.max() >= 1) if config.estimate_clock is None else config.estimate_clock
    if not estimate_clock:
        notes.append(f"clock offset held at {tau0 * 1000:+.1f} ms (not estimated: "
                     + ("a one-way sweep does not separate it from the mount's rotation about the motor axis)"
                        if config.estimate_clock is None else "as asked)"))
    clock.lap("timing")
    fit = partial(solve.solve, marker_radius_m=nominal.marker_radius_m, range_sigma_m=config.range_sigma_m,
                  beam_divergence_rad=nominal.beam_divergence_rad)
    chosen = _servo_alternatives(returns, detections, markers, joints, nominal, config, estimate_clock, fit, clock)
    fit = partial(fit, estimate=chosen.estimate)
    chosen = _in_nominal_representative(_handedness(chosen, nominal.dh, config, fit), nominal.dh, fit)
    notes.extend(chosen.notes)
    if chosen.sign < 0:
        joints = _negated(joints)
    clock.lap("solve", scans=scans, detections=detections, association=chosen.assoc, markers=chosen.markers)
    tried: list[str] = []
    ours, surface_list, on_surfaces = _with_surfaces(chosen, recording, joints, detections, config, fit, tried)
    while off := _most_off(ours, notes, config.max_reduced_chi2):  # estimated in every solve from the marker-only on
        chosen = replace(chosen, estimate=(*chosen.estimate, off))
        fit = partial(fit, estimate=chosen.estimate)
        chosen = replace(chosen, solution=fit(chosen.matched, chosen.markers, chosen.solution.params,
                                              model="sphere", clock=chosen.clock,
                                              clock_offset_s=chosen.solution.clock_offset_s))
        tried = []
        ours, surface_list, on_surfaces = _with_surfaces(chosen, recording, joints, detections, config, fit, tried)
    notes.extend(tried)
    if config.surfaces:
        clock.lap("surfaces")
    checks = marker_checks(ours, chosen.solution, chosen.matched, chosen.markers, passes, config, fit, chosen.clock,
                           nominal.dh)
    checks.append(minima.other_minimum(chosen.solution, chosen.matched, chosen.markers, nominal, config, fit))
    ours = _with_turning_systematic(ours, chosen, nominal, config, fit, notes)  # after the checks: they judge the fit
    baseline = None
    if config.baseline:
        baseline = _baseline(chosen, scans, joints, config, fit, notes)
        clock.lap("baseline")
    return CalibrationResult(
        recording=recording, markers=chosen.markers, detections=detections, observations=chosen.matched,
        association=chosen.assoc, start=chosen.start, solution=ours, baseline=baseline, cloud_before_M=np.zeros((0, 3)),
        cloud_after_M=np.zeros((0, 3)), cloud_intensity=np.zeros(0), geometry_before=None, geometry_after=None,
        surfaces=tuple(surface_list), surface_returns=on_surfaces, checks=tuple(checks), servo_sign=chosen.sign,
        side_by_side={"markers only": chosen.solution,
                      "markers and every plane" if config.all_planes else "markers and their surfaces": ours},
    )


def _with_turning_systematic(ours: Solution, chosen: Alternative, nominal: Nominal, config: CalibConfig,
                             fit: Callable[..., Solution], notes: list[str]) -> Solution:
    """``ours`` with the DH covariance widened by d d^T, d the difference the model variant makes where the sweep
    turns on a marker (lrfcal.model.marker.crossings: only the in-plane part of those crossings' lateral residual,
    solve(in_plane_at_turns=True)), between the two marker-only solutions. The lines of a turning crossing crowd
    about the turning point and bias the part across the scan plane; the variant leaves that part out and loses its
    information, so neither is right alone, and their difference is a model error the noise's sigma does not hold
    (docs/study.md, "A crossing that turns on its marker"). Unchanged where no crossing turns."""
    sol = chosen.solution
    pb, _ = marker_problem(chosen.matched, chosen.markers.positions_W, "sphere", nominal.marker_radius_m,
                           config.range_sigma_m, nominal.beam_divergence_rad)
    th, R_ref = pack(sol.params, sol.clock_offset_s)
    if not np.any(crossings(th, pb.markers, R_ref, chosen.clock)[1]):
        return ours
    try:
        variant = fit(chosen.matched, chosen.markers, sol.params, model="sphere", clock=chosen.clock,
                      clock_offset_s=sol.clock_offset_s, in_plane_at_turns=True)
    except CalibrationError:
        return ours
    d = dh_difference(variant.params.dh.vector(), sol.params.dh.vector())
    notes.append("crossings of the sweep turn on some markers: the DH with only the in-plane part of their lateral "
                 f"residual differ by {dh_text(DH(*d))}, added to the covariance")
    return ours.with_dh_systematic(d)


def _in_nominal_representative(chosen: Alternative, nominal: DH, fit: Callable[..., Solution]) -> Alternative:
    """The marker-only solution in the DH representative nearer the nominal DH: solved again from its turned twin
    (-a, -alpha, b, beta + pi with the mount turned by pi about the motor axis: the same rig, lrfcal.model.kinematics.
    dh_twins) when that twin is nearer. A solve from the mirror image (:func:`_handedness`) or from a coarse start
    can end in the other representative, right as a rig but with a, alpha and beta far from the rig file's."""
    sol = chosen.solution
    if not start.turned_is_nearer(sol.params.dh, nominal):
        return chosen
    _, twin, Q = dh_twins(sol.params.dh)[0]
    turned = Params(Pose.from_matrix(sol.params.mount.matrix() @ homogeneous(Q, np.zeros(3))), twin)
    try:
        new = fit(chosen.matched, chosen.markers, turned, model="sphere", clock=chosen.clock,
                  clock_offset_s=sol.clock_offset_s)
    except CalibrationError:
        return chosen
    return replace(chosen, solution=new)


def _handedness(chosen: Alternative, nominal: DH, config: CalibConfig, fit: Callable[..., Solution]) -> Alternative:
    """The marker-only solution in the marker map's other handedness, when the nominal DH prefer it.

    Tape distances fix the map only up to a reflection. With the map mirrored, the estimate's mirror twin
    (lrfcal.checks.nearer_mirror) explains the data exactly as well, its mount F T_W_M Q (F the map's reflection,
    Q the twin's isometry in M). Near a scan plane perpendicular to the motor axis the association cannot tell the
    handedness, so it is chosen here by the nominal DH: solved again from that twin. The result must then pass the
    mirror check; otherwise the first solution stays (and the check refuses it)."""
    found = nearer_mirror(chosen.solution.params.dh, nominal, config)
    if found is None:
        return chosen
    name, twin, Q, d_est, d_twin = found
    F = np.diag([1.0, 1.0, -1.0, 1.0])
    T = F @ chosen.solution.params.mount.matrix() @ homogeneous(Q, np.zeros(3))
    markers = association.unmirror(chosen.markers)
    try:
        sol = fit(chosen.matched, markers, Params(Pose.from_matrix(T), twin), model="sphere", clock=chosen.clock,
                  clock_offset_s=chosen.solution.clock_offset_s)
    except CalibrationError:
        return chosen
    if not mirror_check(sol.params.dh, nominal, config).passed:
        return chosen
    note = (f"the marker map matched in the other handedness: its mirror image ({name}) is {d_twin:.1f} nominal "
            f"tolerances from the nominal DH, the first estimate {d_est:.1f}; solved again in the map's mirror image")
    assoc = replace(chosen.assoc, mirrored=not chosen.assoc.mirrored, T_W_M=T)
    return replace(chosen, markers=markers, assoc=assoc, solution=sol, notes=(*chosen.notes, note))


def _servo_alternatives(returns: Observations, detections: Detections, markers: MarkerMap, joints: JointStates,
                        nominal: Nominal, config: CalibConfig, estimate_clock: bool, fit: Callable[..., Solution],
                        clock: Stopwatch) -> Alternative:
    """4.-6.: association and marker-only solve for each direction of the servo (the data cannot tell them apart),
    and the direction chosen. The DH search (lrfcal.start) runs only when neither direction associates well from
    the nominal values."""
    signed = {sign: returns if sign > 0 else _replace(returns, lambda_rad=-returns.lambda_rad) for sign in (1, -1)}
    first: dict[int, Association | None] = {}

    def associated(sign: int) -> Association | None:  # from the nominal DH, once, when first needed
        if sign not in first:
            first[sign] = _associate_nominal(signed[sign], detections, markers, nominal, config)
        return first[sign]

    # the DH search runs when neither direction associates well (the other is associated only if the declared fails)
    search = not any((a := associated(s)) is not None and _good(a, signed[s], config) for s in (1, -1))
    clock.lap("association")  # from the nominal DH; the DH search, when needed, counts with the solve
    alternatives = []
    failures = []
    for sign in (1, -1):
        if sign == -1 and alternatives and not far_from_nominal(alternatives[0].solution.params.dh, nominal.dh,
                                                                config):
            break  # the declared direction fits near the nominal: servo_direction keeps it whatever the other gives
        try:
            start_dh, assoc = (_associate_search(signed[sign], detections, markers, nominal, config, associated(sign),
                                                 every_attitude=not alternatives)
                               if search else (nominal.dh, associated(sign)))
            alternatives.append(_marker_solution(sign, start_dh, assoc, markers, signed[sign], joints, nominal,
                                                 config, estimate_clock, fit))
        except CalibrationError as err:
            if sign == 1 and not isinstance(err, _NoMatch):
                raise  # e.g. the layout does not determine the DH: the other direction does not help
            failures.append((sign, err))
    if not alternatives:
        raise failures[0][1]
    return servo_direction(alternatives, nominal.dh, config)


#: an intrinsic scale whose score test steps this many sigma from 1 is estimated (a gear ratio, an angle increment)
SCALE_Z_LIMIT = 4.0
#: what is off when a scale held at 1 by default is not 1 (lrfcal.model.unknowns, kind "intrinsic"). The bearing
#: scale (beam_scale) is not tested: on tunnel_v_systematic the unmodelled range errors move its score test 15 sigma
#: from 1 (0.99147 +- 0.00057, truth 1), and estimating it puts the mount 10 mm off
SCALES = {"motor_scale": "the servo's motor-angle scale (a gear ratio or counts per turn in the joint states?)",
          "range_scale": "the scanner's range scale (ranges off in proportion to their length, or a range bias "
                         "growing with range read as one?)"}


def _most_off(sol: Solution, notes: list[str], max_chi2: float) -> str | None:
    """The scale of :data:`SCALES` held at 1 that the data contradict most (its score test on ``sol``, lrfcal.solve,
    beyond SCALE_Z_LIMIT sigma), named in a note with the value it steps to; None when none is. One at a time, the
    others tested again once it is free: a gear ratio 2 % off also stepped the range scale beyond 4 sigma, which
    it absorbs. None where ``sol``'s reduced chi-square is above ``max_chi2``: a score test means nothing where the
    model does not fit (three times the stated range noise stepped the range scale 4.4 sigma), and the chi-square
    check names that."""
    if not sol.reduced_chi2 <= max_chi2:
        return None
    z = {n: abs(v - 1.0) / s for n, (v, s) in sol.held_score.items() if n in SCALES and math.isfinite(s) and s > 0}
    name = max(z, key=z.__getitem__, default=None)
    if name is None or z[name] <= SCALE_Z_LIMIT:
        return None
    value, sigma = sol.held_score[name]
    notes.append(f"{SCALES[name]} is off: about {value:.5f} +- {sigma:.5f} ({z[name]:.0f} sigma from 1): estimated "
                 "in every solve")
    return name


def _with_surfaces(chosen: Alternative, recording: Recording, joints: JointStates, detections: Detections,
                   config: CalibConfig, fit: Callable[..., Solution], notes: list[str]
                   ) -> tuple[Solution, list[surfaces.Surface], surfaces.SurfaceReturns | None]:
    """6b: every beam on the markers' planes solved jointly with the markers (and every other plane of the scene with
    ``config.all_planes``); the marker-only solution when ``config.surfaces`` is off."""
    ours, markers, matched, motor = chosen.solution, chosen.markers, chosen.matched, chosen.clock
    if not config.surfaces:
        return ours, [], None
    scans, nominal = recording.scans, recording.nominal
    beam_times = scans.beam_times_s
    lambda_beams = timing.motor_angles(beam_times, joints, clock_offset_s=ours.clock_offset_s, tolerance_s=math.inf)
    surface_list, on_surfaces = surfaces.observe_surfaces(
        scans.ranges_m, scans.mu_rad, lambda_beams, detections.labels, markers.positions_W,
        nominal.marker_radius_m, ours.params, position_sigma_m=max(markers.rms_m, 0.0005),
        max_returns=config.surface_max_returns, beam_times_s=beam_times,
        intrinsics=ours.intrinsic_values,
    )
    if len(on_surfaces):
        joint = partial(fit, matched, markers, ours.params, model="sphere", surfaces=on_surfaces,
                        planes=surface_list, clock=motor, clock_offset_s=ours.clock_offset_s, held_scores=tuple(SCALES))
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
            ours = fit(matched, markers, ours.params, model="sphere", surfaces=on_surfaces,
                       planes=surface_list, clock=motor, clock_offset_s=ours.clock_offset_s,
                       estimate_range_bias=math.isfinite(ours.range_offset_sigma_m), held_scores=tuple(SCALES))
            notes.append(f"{len(other_planes)} more planes of the scene ({len(others)} returns) solved jointly as "
                         "free planes")
    return ours, list(surface_list), on_surfaces


def _baseline(chosen: Alternative, scans: Scans, joints: JointStates, config: CalibConfig,
              fit: Callable[..., Solution], notes: list[str]) -> Solution | None:
    """The paper's method: the blob's brightest beam, the motor angle at the scan's stamp, point-to-centre residuals,
    on the same detections and association (None, with a note, when it cannot run)."""
    peaks = chosen.matched.subset(chosen.matched.is_peak)
    lambda_scan = timing.scan_angles(scans, joints, clock_offset_s=config.clock_offset_s)
    peaks = _replace(peaks, lambda_rad=lambda_scan[peaks.scan])
    try:
        return fit(peaks, chosen.markers, chosen.start, model="paper")
    except CalibrationError as err:
        notes.append(f"the paper's method could not be run: {err}")
        return None


def _marker_solution(
    sign: int, start_dh: DH, assoc: Association | None, markers: MarkerMap, returns: Observations,
    joints: JointStates, nominal: Nominal, config: CalibConfig, estimate_clock: bool, fit: Callable[..., Solution],
) -> Alternative:
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
                                       beam_divergence_rad=nominal.beam_divergence_rad, sides=False)
    obs = observability.analyse(info, names, start.dh.alpha)
    if not obs.determined:
        raise CalibrationError(
            f"the recording does not determine {', '.join(obs.undetermined) or 'the DH parameters'} "
            f"({obs.describe()}: 1-sigma {obs.weakest_sigma_in_limits:.3g} times the limit, judged at the start): "
            f"{obs.hint()}"
        )
    fit = partial(fit, held_scores=tuple(SCALES))  # the scales' score tests read this solution (and its re-solves)
    sol = fit(matched, markers, start, model="sphere", clock=motor, clock_offset_s=config.clock_offset_s)
    notes: list[str] = []
    estimate: tuple[str, ...] = ()
    while off := _most_off(sol, notes, config.max_reduced_chi2):  # before any marker is judged moved: a range
        estimate = (*estimate, off)                              # scale moves every far marker from its tape position
        fit = partial(fit, estimate=estimate)
        sol = fit(matched, markers, sol.params, model="sphere", clock=motor, clock_offset_s=sol.clock_offset_s)
    # blobs whose returns the fit rejects (most of them beyond 4 sigma) are matched wrongly or sit on a marker
    # that is not where the tape puts it: unassign them and solve again
    for _ in range(3):  # a blob matched wrongly, or a marker that is not where the tape puts it: out, and again
        bad, why = association.inconsistent_blobs(matched, sol, markers, config.range_sigma_m)
        if not bad.size:
            break
        dh_sigma = sol.sigma[6:10]
        if not observability.within_limits(dh_sigma):  # its residuals cannot tell (fast sweeps went wrong)
            raise CalibrationError(
                f"the marker-only fit disagrees with the marker map ({why.removesuffix(': left out')}), but the "
                "markers alone do not determine the DH parameters here (1-sigma "
                f"{observability.sigma_words(dh_sigma)}), so a wrong match cannot be told from a moved marker: sweep "
                "slower or more passes, so that several scan lines cross every marker")
        notes.append(why)
        b2m = assoc.blob_to_marker.copy()
        b2m[bad] = -1
        assoc = Association(b2m, assoc.mirrored, assoc.T_W_M, assoc.rms_m, int((b2m >= 0).sum()))
        matched = _with_markers(returns, b2m)
        if len(np.unique(matched.marker)) < 4:
            raise CalibrationError(f"{why}; fewer than 4 markers remain")
        sol = fit(matched, markers, sol.params, model="sphere", clock=motor,
                  clock_offset_s=sol.clock_offset_s)
    return Alternative(sign, markers, assoc, matched, start, motor, sol, tuple(notes), estimate)


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


#: the share of the blobs an association matches for it to be the rig's (:func:`_good`, :func:`_associate_search`)
MOST_BLOBS = 0.9


def _matches_most(assoc: Association, returns: Observations) -> bool:
    """Whether an association matches most blobs (MOST_BLOBS of them)."""
    return assoc.n_matched >= MOST_BLOBS * len(np.unique(returns.blob))


def _good(assoc: Association, returns: Observations, config: CalibConfig) -> bool:
    """An association that leaves nothing to search for: most blobs matched, tight alignment."""
    return _matches_most(assoc, returns) and assoc.rms_m <= 0.25 * config.association_gate_m


def _associate_search(returns: Observations, detections: Detections, markers: MarkerMap, nominal: Nominal,
                      config: CalibConfig, from_nominal: Association | None, every_attitude: bool = True
                      ) -> tuple[DH, Association | None]:
    """The association from the candidates of the correspondence-free DH search (lrfcal.start) or from the nominal
    DH, the best by (matched blobs, alignment RMS); returns the DH it used and the association (None: none). The
    search covers the basin around the nominal first, and every attitude of the scan plane (the coarse global start)
    when no candidate there matches most blobs: a nominal DH far from the rig's is then found, not landed on. (An
    association that matches most blobs loosely, e.g. with a marker moved after taping, is the rig's: the solve
    refines it, and the global search, seconds with many blobs, would find nothing better.) ``every_attitude``
    False: the basin only (the servo's other direction, once the declared one has a solution)."""
    best_dh, best = nominal.dh, from_nominal
    for span in (start.ANGLE_SPAN_RAD, start.GLOBAL_SPAN_RAD) if every_attitude else (start.ANGLE_SPAN_RAD,):
        for dh in start.dh_candidates(returns, len(detections.blobs), markers, nominal.dh, nominal.marker_radius_m,
                                      span_rad=span):
            found = _attempt(returns, detections, markers, dh, nominal.marker_radius_m, config)
            if found is not None and (best is None or (found.n_matched, -found.rms_m) > (best.n_matched, -best.rms_m)):
                best_dh, best = dh, found
        if best is not None and _matches_most(best, returns):
            break
    return best_dh, best


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


#: The stages of a calibration with markers in the order they run, as reported to ``progress`` and in
#: CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("mds", "detection", "timing", "association", "solve", "surfaces", "baseline",
                           "reprojection", "geometry")


__all__ = ["STAGES", "Alternative", "fit_markers"]
