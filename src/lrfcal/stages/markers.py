"""Calibration with markers: the seed paper's Sec. III and IV-C as observation sets and a start.

1. markers from tape distances (mds)          5. start: mount pose from that alignment, DH from nominal
2. marker returns in the intensity image      6. the marker returns solved for each direction of the servo
   (detection)                                   (solve), the direction chosen (lrfcal.estimate.checks.servo_direction);
3. per-beam time and motor angle (timing)        then jointly with the surfaces the markers sit on (surfaces),
4. blobs matched to markers (association)        and with every other plane of the scene when asked

The paper's own variant (one max-intensity beam per blob, one motor angle per scan) runs beside ours as the
baseline, on the same detections and association, so that the gain is measured. lrfcal.pipeline runs this and
the shared stages (checks, reprojection, geometry).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.errors import CalibrationError
from lrfcal.estimate import minima, observability, solve
from lrfcal.estimate.checks import (
    dh_text,
    far_from_nominal,
    marker_checks,
    mirror_check,
    nearer_mirror,
    servo_direction,
)
from lrfcal.estimate.information import information_at
from lrfcal.estimate.problem import marker_problem
from lrfcal.model.kinematics import DH, Params, Pose, dh_twins, homogeneous
from lrfcal.model.marker import MarkerSensor, crossings
from lrfcal.model.motor import Clock, MotorClock
from lrfcal.model.unknowns import dh_difference, pack
from lrfcal.result import CalibrationResult, MarkerEvidence
from lrfcal.stages import association, detection, joint, matching, mds, start, surfaces, timing
from lrfcal.types import (
    Association,
    Check,
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
    #: a disagreement with the marker map (in words) that the marker-only fit found but could not judge, as it does
    #: not determine the DH parameters (one scan line per marker): judged at the joint solution (_judged_jointly)
    unjudged: str = ""


#: the joint result (lrfcal.stages.joint.with_surfaces): the solution, the surfaces, their returns
JointFit = tuple[Solution, list[surfaces.Surface], surfaces.SurfaceReturns | None]


@dataclass(frozen=True)
class Observed:
    """The marker way's observations: the marker map, the blobs, every blob's returns with their motor angles, the
    sweep's passes (per scan) and whether the clock offset is estimated."""

    markers: MarkerMap
    detections: Detections
    returns: Observations
    passes: np.ndarray
    estimate_clock: bool


class MarkerWay:
    """Calibration with markers as the steps of lrfcal.pipeline's orchestrator: observe (stages 1-3: the marker map,
    the marker returns, their times), starts (4.-6.: the marker-only solve from each candidate start, servo direction,
    handedness, DH representative), refine (6b: jointly with the surfaces, scales the data contradict, the blobs the
    marker-only fit could not judge), checks (and the turning systematic, the paper's baseline): a result without
    clouds (lrfcal.pipeline adds them). Raises CalibrationError: no marker returns, no match, or the layout does not
    determine the DH parameters."""

    STAGES: tuple[str, ...] = ()  # set below the module's STAGES

    def __init__(self, recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch,
                 notes: list[str]) -> None:
        self.recording, self.joints, self.config, self.clock, self.notes = recording, joints, config, clock, notes
        nominal = recording.nominal
        self.fit = solve.Solver(MarkerSensor.of("sphere", nominal.marker_radius_m, nominal.beam_divergence_rad,
                                                config.range_sigma_m))

    def ahead(self) -> contextlib.AbstractContextManager[None]:
        """Nothing runs ahead of the marker way."""
        return contextlib.nullcontext()

    def observe(self) -> Observed:
        """Stages 1-3: the marker map, the blobs, the marker returns with their motor angles."""
        recording, joints, config, clock = self.recording, self.joints, self.config, self.clock
        scans, tau0 = recording.scans, config.clock_offset_s
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
            self.notes.append(f"clock offset held at {tau0 * 1000:+.1f} ms (not estimated: "
                              + ("a one-way sweep does not separate it from the mount's rotation about the motor "
                                 "axis)" if config.estimate_clock is None else "as asked)"))
        clock.lap("timing")
        self.observed = Observed(markers, detections, returns, passes, estimate_clock)
        return self.observed

    def starts(self, observed: Observed) -> Alternative:
        """4.-6.: the marker-only solution from each candidate start (servo direction, handedness, DH
        representative), the one chosen."""
        nominal = self.recording.nominal
        chosen = _servo_alternatives(observed.returns, observed.detections, observed.markers,
                                     self.joints if observed.estimate_clock else None, nominal, self.config,
                                     self.fit, self.clock)
        self.fit = self.fit.but(estimate=chosen.estimate)
        chosen = _in_nominal_representative(_handedness(chosen, nominal.dh, self.config, self.fit), nominal.dh,
                                            self.fit)
        self.notes.extend(chosen.notes)
        if chosen.sign < 0:
            self.joints = _negated(self.joints)
        self.clock.lap("solve", scans=self.recording.scans, detections=observed.detections,
                       association=chosen.assoc, markers=chosen.markers)
        return chosen

    def refine(self, chosen: Alternative) -> tuple[Alternative, JointFit]:
        """6b: the sets chosen again until stable (lrfcal.stages.joint, :func:`_jointly`)."""
        recorded = joint.Recorded(self.recording, self.joints, self.observed.detections)
        chosen, self.fit, joint_fit = _jointly(chosen, recorded, self.config, self.fit, self.notes)
        if self.config.surfaces:
            self.clock.lap("surfaces")
        return chosen, joint_fit

    def checks(self, refined: tuple[Alternative, JointFit], shared: Callable[[Solution], Check]
               ) -> CalibrationResult:
        """The checks (``shared``: those of both ways, first), the turning systematic, the paper's baseline: the
        result without clouds."""
        chosen, (ours, surface_list, on_surfaces) = refined
        config, fit, nominal = self.config, self.fit, self.recording.nominal
        checks = marker_checks(ours, chosen.solution, chosen.matched, chosen.markers, self.observed.passes, config, fit,
                               nominal.dh)
        checks.append(minima.other_minimum(chosen.solution, chosen.matched, chosen.markers, nominal, config, fit))
        ours = _with_turning_systematic(ours, chosen, fit, self.notes)  # after the checks: they judge the fit
        baseline = None
        if config.baseline:
            baseline = _baseline(chosen, self.recording.scans, self.joints, config, fit, self.notes)
            self.clock.lap("baseline")
        evidence = MarkerEvidence(markers=chosen.markers, detections=self.observed.detections,
                                  observations=chosen.matched, association=chosen.assoc, baseline=baseline,
                                  surfaces=tuple(surface_list), surface_returns=on_surfaces)
        return CalibrationResult(
            recording=self.recording, evidence=evidence, start=chosen.start, solution=ours,
            checks=(shared(ours), *checks),
            servo_sign=chosen.sign,
            side_by_side={"markers only": chosen.solution,
                          "markers and every plane" if config.all_planes else "markers and their surfaces": ours},
        )


def _with_turning_systematic(ours: Solution, chosen: Alternative, fit: solve.Solver, notes: list[str]) -> Solution:
    """``ours`` with the DH covariance widened by d d^T, d the difference the model variant makes where the sweep
    turns on a marker (lrfcal.model.marker.crossings: only the in-plane part of those crossings' lateral residual,
    solve(in_plane_at_turns=True)), between the two marker-only solutions. The lines of a turning crossing crowd
    about the turning point and bias the part across the scan plane; the variant leaves that part out and loses its
    information, so neither is right alone, and their difference is a model error the noise's sigma does not hold
    (docs/study.md, "A crossing that turns on its marker"). Unchanged where no crossing turns."""
    sol = chosen.solution
    pb, _ = marker_problem(chosen.matched, chosen.markers.positions_W, fit.sensor)
    th, R_ref = pack(sol.params, sol.clock_offset_s)
    if not np.any(crossings(th, pb.markers, R_ref, chosen.clock)[1]):
        return ours
    try:
        variant = fit(chosen.matched, chosen.markers, sol.params, clock=Clock(chosen.clock, sol.clock_offset_s),
                      in_plane_at_turns=True)
    except CalibrationError:
        return ours
    d = dh_difference(variant.params.dh.vector(), sol.params.dh.vector())
    notes.append("crossings of the sweep turn on some markers: the DH with only the in-plane part of their lateral "
                 f"residual differ by {dh_text(DH(*d))}, added to the covariance")
    return ours.with_dh_systematic(d)


def _in_nominal_representative(chosen: Alternative, nominal: DH, fit: solve.Solver) -> Alternative:
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
        new = fit(chosen.matched, chosen.markers, turned, clock=Clock(chosen.clock, sol.clock_offset_s))
    except CalibrationError:
        return chosen
    return replace(chosen, solution=new)


def _handedness(chosen: Alternative, nominal: DH, config: CalibConfig, fit: solve.Solver) -> Alternative:
    """The marker-only solution in the marker map's other handedness, when the nominal DH prefer it.

    Tape distances fix the map only up to a reflection. With the map mirrored, the estimate's mirror twin
    (lrfcal.estimate.checks.nearer_mirror) explains the data exactly as well, its mount F T_W_M Q (F the map's
    reflection,
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
        sol = fit(chosen.matched, markers, Params(Pose.from_matrix(T), twin),
                  clock=Clock(chosen.clock, chosen.solution.clock_offset_s))
    except CalibrationError:
        return chosen
    if not mirror_check(sol.params.dh, nominal, config).passed:
        return chosen
    note = (f"the marker map matched in the other handedness: its mirror image ({name}) is {d_twin:.1f} nominal "
            f"tolerances from the nominal DH, the first estimate {d_est:.1f}; solved again in the map's mirror image")
    assoc = replace(chosen.assoc, mirrored=not chosen.assoc.mirrored, T_W_M=T)
    return replace(chosen, markers=markers, assoc=assoc, solution=sol, notes=(*chosen.notes, note))


def _servo_alternatives(returns: Observations, detections: Detections, markers: MarkerMap,
                        joints: JointStates | None, nominal: Nominal, config: CalibConfig, fit: solve.Solver,
                        clock: Stopwatch) -> Alternative:
    """4.-6.: association and marker-only solve for each direction of the servo (the data cannot tell them apart),
    and the direction chosen; ``joints``: the joint states the clock offset is estimated by (None: held). The DH
    search (lrfcal.stages.start) runs only when neither direction associates well from the nominal values."""
    signed = {sign: returns if sign > 0 else _replace(returns, lambda_rad=-returns.lambda_rad) for sign in (1, -1)}
    first: dict[int, Association | None] = {}

    def associated(sign: int) -> Association | None:  # from the nominal DH, once, when first needed
        if sign not in first:
            first[sign] = matching.associate_nominal(signed[sign], detections, markers, nominal, config)
        return first[sign]

    # the DH search runs when neither direction associates well (the other is associated only if the declared fails)
    search = not any((a := associated(s)) is not None and matching.good(a, signed[s], config) for s in (1, -1))
    clock.lap("association")  # from the nominal DH; the DH search, when needed, counts with the solve
    alternatives = []
    failures = []
    for sign in (1, -1):
        if sign == -1 and alternatives and not far_from_nominal(alternatives[0].solution.params.dh, nominal.dh,
                                                                config):
            break  # the declared direction fits near the nominal: servo_direction keeps it whatever the other gives
        try:
            start_dh, assoc = (matching.associate_search(signed[sign], detections, markers, nominal, config,
                                                         associated(sign), every_attitude=not alternatives)
                               if search else (nominal.dh, associated(sign)))
            alternatives.append(_marker_solution(sign, start_dh, assoc, markers, signed[sign], joints, config, fit))
        except CalibrationError as err:
            if sign == 1 and not isinstance(err, _NoMatch):
                raise  # e.g. the layout does not determine the DH: the other direction does not help
            failures.append((sign, err))
    if not alternatives:
        raise failures[0][1]
    return servo_direction(alternatives, nominal.dh, config)


def _jointly(chosen: Alternative, recorded: joint.Recorded, config: CalibConfig, fit: solve.Solver, notes: list[str]
             ) -> tuple[Alternative, solve.Solver, tuple[Solution, list[surfaces.Surface],
                                                                  surfaces.SurfaceReturns | None]]:
    """6b (lrfcal.stages.joint) from ``chosen``'s marker-only solution, again from the marker-only fit on with a scale
    the
    data contradict estimated (lrfcal.stages.joint.most_off); then the disagreement with the marker map that the
    marker-only fit found but could not judge (``chosen.unjudged``) judged at the joint solution. ``chosen`` and
    ``fit`` as they end up, and the joint result (lrfcal.stages.joint.with_surfaces)."""
    while True:
        tried: list[str] = []
        joint_fit = joint.with_surfaces(chosen.solution, chosen.matched, chosen.markers, chosen.clock, recorded,
                                        config, fit, tried)
        if not (off := joint.most_off(joint_fit[0], notes, config.max_reduced_chi2)):
            break
        chosen = replace(chosen, estimate=(*chosen.estimate, off))  # estimated in every solve from the start on
        fit = fit.but(estimate=chosen.estimate)
        chosen = replace(chosen, solution=_refit(chosen, chosen.matched, fit))
    if chosen.unjudged:
        chosen, joint_fit, tried = _judged_jointly(chosen, joint_fit, recorded, config, fit, notes)
    notes.extend(tried)
    return chosen, fit, joint_fit


def _judged_jointly(chosen: Alternative, joint_fit: tuple[Solution, list[surfaces.Surface],
                                                          surfaces.SurfaceReturns | None],
                    recorded: joint.Recorded, config: CalibConfig, fit: solve.Solver, notes: list[str]
                    ) -> tuple[Alternative, tuple[Solution, list[surfaces.Surface], surfaces.SurfaceReturns | None],
                               list[str]]:
    """The disagreement with the marker map that ``chosen``'s marker-only fit found but could not judge, as it does
    not determine the DH parameters (one scan line per marker: there a wrong match cannot be told from a moved
    marker, and a good marker can look moved), judged at the joint solution ``joint_fit``, whose surfaces determine
    them: the blobs that disagree there (lrfcal.stages.association.inconsistent_blobs) left out and solved again, at
    most
    three times. Where no surface returns lie where the marker-only fit puts them (a wrong match can pull it far),
    the joint solution starts from the marker-only fit without the blobs it finds disagreeing, and every blob is
    judged from there. ``chosen`` with the blobs so kept, the joint result and its notes.

    Raises:
        CalibrationError: no surface returns to judge by, or blobs that still disagree after three are left out.
    """
    assoc, matched, start = chosen.assoc, chosen.matched, joint_fit[0]
    if start is chosen.solution:  # no surface returns where the marker-only fit puts them: try it without the blobs
        sol, kept = chosen.solution, (assoc, matched)  # it finds disagreeing, for a start only
        for _ in range(3):
            bad, why = association.inconsistent_blobs(kept[1], sol, chosen.markers, config.range_sigma_m)
            if not bad.size:
                break
            kept = _without_blobs(*kept, bad, why)
            sol = fit(kept[1], chosen.markers, sol.params, clock=Clock(chosen.clock, sol.clock_offset_s))
            if (start := joint.with_surfaces(sol, kept[1], chosen.markers, chosen.clock, recorded, config, fit,
                                             [])[0]) is not sol:
                break
    no_surfaces = CalibrationError(observability.unjudged_refusal(
        _observability(chosen.solution), "the markers alone", "and no surface returns were found to add",
        chosen.unjudged))
    if start is chosen.solution or start.n_surface_returns == 0:
        raise no_surfaces
    for left_out in range(4):  # every round from that start: one with a wrong blob in can be far off
        tried: list[str] = []
        joint_fit = joint.with_surfaces(start, matched, chosen.markers, chosen.clock, recorded, config, fit, tried)
        if joint_fit[0] is start:  # no surface returns for these blobs
            raise no_surfaces
        bad, why = association.inconsistent_blobs(matched, joint_fit[0], chosen.markers, config.range_sigma_m)
        if not bad.size:
            if not left_out:
                notes.append(f"the marker-only fit disagreed with the marker map ({chosen.unjudged}); the joint "
                             "solution with the surfaces does not (the markers alone do not determine the DH "
                             "parameters here)")
            break
        if left_out == 3:
            raise CalibrationError(observability.unjudged_refusal(  # what leads: the cause the data support
                _observability(joint_fit[0]), "the markers and the surfaces they sit on", "",
                f"{why.removesuffix(': left out')}, judged at the joint solution with the surfaces, after three "
                "blobs were left out"))
        notes.append(f"{why} (judged at the joint solution with the surfaces)")
        assoc, matched = _without_blobs(assoc, matched, bad, why)
    chosen = replace(chosen, assoc=assoc, matched=matched, unjudged="", solution=_refit(chosen, matched, fit))
    return chosen, joint_fit, tried


def _observability(sol: Solution) -> observability.Observability:
    return observability.of_solution(sol.information, sol.information_names, sol.sigma[6:10], sol.params.dh.alpha)


def _without_blobs(assoc: Association, matched: Observations, bad: np.ndarray, why: str
                   ) -> tuple[Association, Observations]:
    """``assoc`` and its ``matched`` returns with the blobs ``bad`` unassigned (``why``: what is wrong with them).

    Raises:
        CalibrationError: fewer than 4 markers remain.
    """
    b2m = assoc.blob_to_marker.copy()
    b2m[bad] = -1
    matched = matched.subset(b2m[matched.blob] >= 0)
    if len(np.unique(matched.marker)) < 4:
        raise CalibrationError(f"{why}; fewer than 4 markers remain")
    return replace(assoc, blob_to_marker=b2m, n_matched=int((b2m >= 0).sum())), matched


def _refit(chosen: Alternative, matched: Observations, fit: solve.Solver) -> Solution:
    """``chosen``'s marker-only solution solved again for ``matched``, from itself."""
    return fit(matched, chosen.markers, chosen.solution.params,
               clock=Clock(chosen.clock, chosen.solution.clock_offset_s))


def _baseline(chosen: Alternative, scans: Scans, joints: JointStates, config: CalibConfig,
              fit: solve.Solver, notes: list[str]) -> Solution | None:
    """The paper's method: the blob's brightest beam, the motor angle at the scan's stamp, point-to-centre residuals,
    on the same detections and association (None, with a note, when it cannot run)."""
    peaks = chosen.matched.subset(chosen.matched.is_peak)
    lambda_scan = timing.scan_angles(scans, joints, clock_offset_s=config.clock_offset_s)
    peaks = _replace(peaks, lambda_rad=lambda_scan[peaks.scan])
    try:
        return fit.paper()(peaks, chosen.markers, chosen.start)
    except CalibrationError as err:
        notes.append(f"the paper's method could not be run: {err}")
        return None


def _marker_solution(
    sign: int, start_dh: DH, assoc: Association | None, markers: MarkerMap, returns: Observations,
    joints: JointStates | None, config: CalibConfig, fit: solve.Solver,
) -> Alternative:
    """Start, observability check and marker-only solve for one direction of the servo (``returns`` with their
    motor angles already signed), from the association made with ``start_dh``; ``joints``: the joint states the
    clock offset is estimated by (None: held).

    Raises CalibrationError when the blobs could not be matched, when the data do not determine the DH parameters
    (judged at the start, before any solver runs), or when blobs disagree with the marker map beyond repair.
    """
    if assoc is None:
        raise _NoMatch("association: no alignment of the blobs with the marker map (check the tape "
                               "distances' file and unit, and the marker radius)")
    if assoc.mirrored:
        markers = association.unmirror(markers)
    matched = _with_markers(returns, assoc.blob_to_marker)
    n_matched = len(np.unique(matched.marker))
    if n_matched < 4:
        raise _NoMatch(
            f"only {n_matched} markers matched to detections (need >= 4); alignment RMS {assoc.rms_m * 1000:.1f} mm"
        )
    start = Params(Pose.from_matrix(assoc.T_W_M), start_dh)  # 5.
    motor = None if joints is None else MotorClock.from_joints(joints if sign > 0 else _negated(joints))
    info, names = information_at(matched, markers.positions_W, start, sensor=fit.sensor,
                                 clock=Clock(motor, config.clock_offset_s), sides=False)
    obs = observability.analyse(info, names, start.dh.alpha)
    if not obs.determined:
        raise CalibrationError(
            f"the recording does not determine {', '.join(obs.undetermined) or 'the DH parameters'} "
            f"({obs.describe()}: 1-sigma {obs.weakest_sigma_in_limits:.3g} times the limit, judged at the start): "
            f"{obs.hint()}"
        )
    fit = fit.but(held_scores=tuple(joint.SCALES))  # the scales' score tests read this solution (and re-solves)
    sol = fit(matched, markers, start, clock=Clock(motor, config.clock_offset_s))
    notes: list[str] = []
    estimate: tuple[str, ...] = ()
    while off := joint.most_off(sol, notes, config.max_reduced_chi2):  # before any marker is judged moved: a range
        estimate = (*estimate, off)                              # scale moves every far marker from its tape position
        fit = fit.but(estimate=estimate)
        sol = fit(matched, markers, sol.params, clock=Clock(motor, sol.clock_offset_s))
    # blobs whose returns the fit rejects (most of them beyond 4 sigma) are matched wrongly or sit on a marker
    # that is not where the tape puts it: unassign them and solve again
    for _ in range(3):  # a blob matched wrongly, or a marker that is not where the tape puts it: out, and again
        bad, why = association.inconsistent_blobs(matched, sol, markers, config.range_sigma_m)
        if not bad.size:
            break
        if not observability.within_limits(sol.sigma[6:10]):  # its residuals cannot tell: the joint solution will
            return Alternative(sign, markers, assoc, matched, start, motor, sol, tuple(notes), estimate,
                               unjudged=why.removesuffix(": left out"))
        notes.append(why)
        assoc, matched = _without_blobs(assoc, matched, bad, why)
        sol = fit(matched, markers, sol.params, clock=Clock(motor, sol.clock_offset_s))
    return Alternative(sign, markers, assoc, matched, start, motor, sol, tuple(notes), estimate)


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


MarkerWay.STAGES = STAGES

__all__ = ["STAGES", "Alternative", "MarkerWay", "Observed"]
