"""Calibration with markers: the seed paper's Sec. III and IV-C as observation sets and a start.

1. markers from tape distances (mds)          5. start: mount pose from that alignment, DH from nominal
2. marker returns in the intensity image      6. the marker returns solved for each direction of the servo
   (detection)                                   (solve), the direction chosen (lrfcal.estimate.checks.servo_direction);
3. per-beam time and motor angle (timing)        then jointly with the surfaces the markers sit on (surfaces),
4. blobs matched to markers (association)        and with every other plane of the scene when asked

The paper's own variant (one max-intensity beam per blob, one motor angle per scan) runs beside ours as the
baseline, on the same detections and association, so that the gain is measured. lrfcal.pipeline runs this and
the shared stages (checks, reprojection, geometry); the start's alternatives (4.-6.) are lrfcal.stages.alternatives.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.errors import CalibrationError
from lrfcal.estimate import minima, observability, solve
from lrfcal.estimate.checks import dh_text, marker_checks
from lrfcal.estimate.problem import marker_problem
from lrfcal.model.kinematics import DH
from lrfcal.model.marker import MarkerSensor, crossings
from lrfcal.model.motor import Clock
from lrfcal.model.unknowns import dh_difference, pack
from lrfcal.result import CalibrationResult, MarkerEvidence
from lrfcal.stages import alternatives, association, detection, joint, mds, timing
from lrfcal.stages.alternatives import Alternative
from lrfcal.stages.joint import JointFit
from lrfcal.types import Check, Detections, JointStates, MarkerMap, Noted, Observations, Recording, Scans, Solution


@dataclass(frozen=True)
class Observed:
    """The marker way's observations: the marker map, the blobs, every blob's returns with their motor angles, the
    sweep's passes (per scan) and whether the clock offset is estimated."""

    markers: MarkerMap
    detections: Detections
    returns: Observations
    passes: np.ndarray
    estimate_clock: bool
    notes: tuple[str, ...] = ()  # what observing them noted (the clock offset held)


#: the starts step's outcome: the observations and the alternative chosen
Started = tuple[Observed, Alternative]
#: the refine step's outcome: the observations, the alternative as it ends up and the joint result
Refined = tuple[Observed, Alternative, JointFit]


class MarkerWay:
    """Calibration with markers as the steps of lrfcal.pipeline's orchestrator: observe (stages 1-3: the marker map,
    the marker returns, their times), starts (4.-6.: the marker-only solve from each candidate start, servo direction,
    handedness, DH representative), refine (6b: jointly with the surfaces, scales the data contradict, the blobs the
    marker-only fit could not judge), checks (and the turning systematic, the paper's baseline): a result without
    clouds (lrfcal.pipeline adds them). Raises CalibrationError: no marker returns, no match, or the layout does not
    determine the DH parameters."""

    STAGES: tuple[str, ...] = ()  # set below the module's STAGES
    NOTES: tuple[str, ...] = ()  # what every calibration with markers notes first: nothing

    def __init__(self, recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch) -> None:
        self.recording, self.joints, self.config, self.clock = recording, joints, config, clock
        nominal = recording.nominal
        assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        self.fit = solve.Solver(MarkerSensor.of("sphere", nominal.marker_radius_m, nominal.beam_divergence_rad,
                                                config.range_sigma_m))

    def ahead(self) -> contextlib.AbstractContextManager[None]:
        """Nothing runs ahead of the marker way."""
        return contextlib.nullcontext()

    def observe(self, ahead: None) -> Observed:
        """Stages 1-3: the marker map, the blobs, the marker returns with their motor angles (``ahead``: nothing runs
        ahead)."""
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
        held = () if estimate_clock else (
            f"clock offset held at {tau0 * 1000:+.1f} ms (not estimated: "
            + ("a one-way sweep does not separate it from the mount's rotation about the motor axis)"
               if config.estimate_clock is None else "as asked)"),)
        clock.lap("timing")
        return Observed(markers, detections, returns, passes, estimate_clock, held)

    def starts(self, observed: Observed) -> Started:
        """4.-6.: the marker-only solution from each candidate start (servo direction, handedness, DH
        representative), the one chosen."""
        nominal = self.recording.nominal
        chosen = alternatives.servo_alternatives(observed.returns, observed.detections, observed.markers,
                                     self.joints if observed.estimate_clock else None, nominal, self.config,
                                     self.fit, self.clock)
        fit = self._fit(chosen)
        chosen = alternatives.in_nominal_representative(alternatives.handedness(chosen, nominal.dh, self.config, fit),
                                                        nominal.dh, fit)
        self.clock.lap("solve", scans=self.recording.scans, detections=observed.detections,
                       association=chosen.assoc, markers=chosen.markers)
        return observed, chosen

    def refine(self, started: Started) -> Refined:
        """6b: the sets chosen again until stable (lrfcal.stages.joint, :func:`_jointly`); the refinement's notes
        follow the start's in the alternative's."""
        observed, chosen = started
        recorded = joint.Recorded(self.recording, _signed(self.joints, chosen.sign), observed.detections)
        jointly = _jointly(chosen, recorded, self.config, self._fit(chosen))
        (chosen, joint_fit), notes = jointly.value, jointly.notes
        if self.config.surfaces:
            self.clock.lap("surfaces")
        return observed, replace(chosen, notes=(*chosen.notes, *notes)), joint_fit

    def _fit(self, chosen: Alternative) -> solve.Solver:
        """The marker solve for ``chosen``: the rig's, estimating the unknowns ``chosen`` found the data need."""
        return self.fit.but(estimate=chosen.estimate)

    def checks(self, refined: Refined, shared: Callable[[Solution], Check]) -> CalibrationResult:
        """The checks (``shared``: those of both ways, first), the turning systematic, the paper's baseline: the
        result without clouds."""
        observed, chosen, (ours, surface_list, on_surfaces) = refined
        config, fit, nominal = self.config, self._fit(chosen), self.recording.nominal
        checks = marker_checks(ours, chosen.solution, chosen.matched, chosen.markers, observed.passes, config, fit,
                               nominal.dh)
        checks.append(minima.other_minimum(chosen.solution, chosen.matched, chosen.markers, nominal, config, fit))
        turning = _with_turning_systematic(ours, chosen, fit)  # after the checks: they judge the fit
        baseline: Noted[Solution | None]
        ours, baseline = turning.value, Noted(None)
        if config.baseline:
            baseline = _baseline(chosen, self.recording.scans, _signed(self.joints, chosen.sign), config.clock_offset_s,
                                 fit)
            self.clock.lap("baseline")
        evidence = MarkerEvidence(markers=chosen.markers, detections=observed.detections,
                                  observations=chosen.matched, association=chosen.assoc, baseline=baseline.value,
                                  surfaces=tuple(surface_list), surface_returns=on_surfaces)
        return CalibrationResult(
            recording=self.recording, evidence=evidence, start=chosen.start, solution=ours,
            checks=(shared(ours), *checks),
            servo_sign=chosen.sign, notes=(*observed.notes, *chosen.notes, *turning.notes, *baseline.notes),
            side_by_side={"markers only": chosen.solution,
                          "markers and every plane" if config.all_planes else "markers and their surfaces": ours},
        )


def _with_turning_systematic(ours: Solution, chosen: Alternative, fit: solve.Solver) -> Noted[Solution]:
    """``ours`` with the DH covariance widened by d d^T, d the difference the model variant makes where the sweep
    turns on a marker (lrfcal.model.marker.crossings: only the in-plane part of those crossings' lateral residual,
    solve(in_plane_at_turns=True)), between the two marker-only solutions. The lines of a turning crossing crowd
    about the turning point and bias the part across the scan plane; the variant leaves that part out and loses its
    information, so neither is right alone, and their difference is a model error the noise's sigma does not hold
    (docs/study.md, "A crossing that turns on its marker"), with a note saying so. Unchanged where no crossing
    turns."""
    sol = chosen.solution
    pb, _ = marker_problem(chosen.matched, chosen.markers.positions_W, fit.sensor)
    th, R_ref = pack(sol.params, sol.clock_offset_s)
    assert pb.markers is not None  # a problem of marker returns
    if not np.any(crossings(th, pb.markers, R_ref, chosen.clock)[1]):
        return Noted(ours)
    try:
        variant = fit(chosen.matched, chosen.markers, sol.params, clock=Clock(chosen.clock, sol.clock_offset_s),
                      in_plane_at_turns=True)
    except CalibrationError:
        return Noted(ours)
    d = dh_difference(variant.params.dh.vector(), sol.params.dh.vector())
    return Noted(ours.with_dh_systematic(d), (
        "crossings of the sweep turn on some markers: the DH with only the in-plane part of their lateral residual "
        f"differ by {dh_text(DH(*d))}, added to the covariance",))


class RefineConfig(joint.JointConfig, Protocol):
    """What the marker way's refinement reads (:func:`_jointly`): the joint solve's options
    (lrfcal.stages.joint.JointConfig) and the chi-square limit of the scales' score tests."""

    @property
    def max_reduced_chi2(self) -> float: ...


def _jointly(chosen: Alternative, recorded: joint.Recorded, config: RefineConfig, fit: solve.Solver
             ) -> Noted[tuple[Alternative, JointFit]]:
    """6b (lrfcal.stages.joint) from ``chosen``'s marker-only solution, again from the marker-only fit on with a scale
    the
    data contradict estimated (lrfcal.stages.joint.most_off); then the disagreement with the marker map that the
    marker-only fit found but could not judge (``chosen.unjudged``) judged at the joint solution. ``chosen`` as it
    ends up (its solve: ``fit`` estimating ``chosen.estimate``), and the joint result
    (lrfcal.stages.joint.with_surfaces), with their notes: the scales found off, the blobs judged, the joint
    solve's."""
    notes: list[str] = []
    while True:
        joint_fit = joint.with_surfaces(chosen.solution, chosen.matched, chosen.markers, chosen.clock, recorded,
                                        config, fit)
        if not (off := joint.most_off(joint_fit.value[0], config.max_reduced_chi2)):
            break
        notes += off.notes
        chosen = replace(chosen, estimate=(*chosen.estimate, off.value))  # estimated in every solve from then on
        fit = fit.but(estimate=chosen.estimate)
        chosen = replace(chosen, solution=_refit(chosen, chosen.matched, fit))
    if chosen.unjudged:
        chosen, joint_fit, judged = _judged_jointly(chosen, joint_fit.value, recorded, config, fit)
        notes += judged
    return Noted((chosen, joint_fit.value), (*notes, *joint_fit.notes))


def _judged_jointly(chosen: Alternative, joint_fit: JointFit, recorded: joint.Recorded, config: joint.JointConfig,
                    fit: solve.Solver) -> tuple[Alternative, Noted[JointFit], tuple[str, ...]]:
    """The disagreement with the marker map that ``chosen``'s marker-only fit found but could not judge, as it does
    not determine the DH parameters (one scan line per marker: there a wrong match cannot be told from a moved
    marker, and a good marker can look moved), judged at the joint solution ``joint_fit``, whose surfaces determine
    them: the blobs that disagree there (lrfcal.stages.association.inconsistent_blobs) left out and solved again, at
    most
    three times. Where no surface returns lie where the marker-only fit puts them (a wrong match can pull it far),
    the joint solution starts from the marker-only fit without the blobs it finds disagreeing, and every blob is
    judged from there. ``chosen`` with the blobs so kept, the joint result (with the joint solve's notes) and the
    judgement's notes.

    Raises:
        CalibrationError: no surface returns to judge by, or blobs that still disagree after three are left out.
    """
    assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    assoc, matched, start = chosen.assoc, chosen.matched, joint_fit[0]
    if start is chosen.solution:  # no surface returns where the marker-only fit puts them: try it without the blobs
        sol, kept = chosen.solution, (assoc, matched)  # it finds disagreeing, for a start only
        for _ in range(3):
            bad, why = association.inconsistent_blobs(kept[1], sol, chosen.markers, config.range_sigma_m)
            if not bad.size:
                break
            kept = alternatives.without_blobs(*kept, bad, why)
            sol = fit(kept[1], chosen.markers, sol.params, clock=Clock(chosen.clock, sol.clock_offset_s))
            if (start := joint.with_surfaces(sol, kept[1], chosen.markers, chosen.clock, recorded, config,
                                             fit).value[0]) is not sol:
                break
    no_surfaces = CalibrationError(observability.unjudged_refusal(
        _observability(chosen.solution), "the markers alone", "and no surface returns were found to add",
        chosen.unjudged))
    if start is chosen.solution or start.n_surface_returns == 0:
        raise no_surfaces
    notes: list[str] = []
    for left_out in range(4):  # every round from that start: one with a wrong blob in can be far off
        tried = joint.with_surfaces(start, matched, chosen.markers, chosen.clock, recorded, config, fit)
        if tried.value[0] is start:  # no surface returns for these blobs
            raise no_surfaces
        bad, why = association.inconsistent_blobs(matched, tried.value[0], chosen.markers, config.range_sigma_m)
        if not bad.size:
            if not left_out:
                notes.append(f"the marker-only fit disagreed with the marker map ({chosen.unjudged}); the joint "
                             "solution with the surfaces does not (the markers alone do not determine the DH "
                             "parameters here)")
            break
        if left_out == 3:
            raise CalibrationError(observability.unjudged_refusal(  # what leads: the cause the data support
                _observability(tried.value[0]), "the markers and the surfaces they sit on", "",
                f"{why.removesuffix(': left out')}, judged at the joint solution with the surfaces, after three "
                "blobs were left out"))
        notes.append(f"{why} (judged at the joint solution with the surfaces)")
        assoc, matched = alternatives.without_blobs(assoc, matched, bad, why)
    chosen = replace(chosen, assoc=assoc, matched=matched, unjudged="", solution=_refit(chosen, matched, fit))
    return chosen, tried, tuple(notes)


def _observability(sol: Solution) -> observability.Observability:
    return observability.of_solution(sol.information, sol.information_names, sol.sigma[6:10], sol.params.dh.alpha)


def _refit(chosen: Alternative, matched: Observations, fit: solve.Solver) -> Solution:
    """``chosen``'s marker-only solution solved again for ``matched``, from itself."""
    return fit(matched, chosen.markers, chosen.solution.params,
               clock=Clock(chosen.clock, chosen.solution.clock_offset_s))


def _baseline(chosen: Alternative, scans: Scans, joints: JointStates, clock_offset_s: float, fit: solve.Solver
              ) -> Noted[Solution | None]:
    """The paper's method: the blob's brightest beam, the motor angle at the scan's stamp, point-to-centre residuals,
    on the same detections and association, the motor angles at the clock offset ``clock_offset_s`` [s] (None, with
    a note, when it cannot run)."""
    peaks = chosen.matched.subset(chosen.matched.is_peak)
    lambda_scan = timing.scan_angles(scans, joints, clock_offset_s=clock_offset_s)
    peaks = alternatives.replace_arrays(peaks, lambda_rad=lambda_scan[peaks.scan])
    try:
        return Noted(fit.paper()(peaks, chosen.markers, chosen.start))
    except CalibrationError as err:
        return Noted(None, (f"the paper's method could not be run: {err}",))


def _signed(joints: JointStates, sign: int) -> JointStates:
    """``joints`` with the servo's direction ``sign`` applied."""
    return joints if sign > 0 else alternatives.negated(joints)


#: The stages of a calibration with markers in the order they run, as reported to ``progress`` and in
#: CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("mds", "detection", "timing", "association", "solve", "surfaces", "baseline",
                           "reprojection", "geometry")


MarkerWay.STAGES = STAGES

__all__ = ["STAGES", "Alternative", "MarkerWay", "Observed", "RefineConfig", "Refined", "Started"]
