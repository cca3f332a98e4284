"""Calibration with markers: the seed paper's Sec. III and IV-C as the steps of lrfcal.pipeline's loop.

1. markers from tape distances (mds)          5. start: mount pose from that alignment, DH from nominal
2. marker returns in the intensity image      6. the marker returns solved for each direction of the servo,
   (detection)                                   the direction chosen (lrfcal.stages.alternatives); then jointly
3. per-beam time and motor angle (timing)        with the surfaces the markers sit on, and with every other plane
4. blobs matched to markers (association)        of the scene when asked (lrfcal.stages.refinement)

The paper's own variant (one max-intensity beam per blob, one motor angle per scan) runs beside ours as the
baseline, on the same detections and association, so that the gain is measured. Nothing here solves: each step
returns what to estimate (lrfcal.estimate.request) or what it chose, and lrfcal.pipeline solves it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import ClassVar, Protocol

import numpy as np

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.errors import CalibrationError
from lrfcal.estimate.checks import marker_checks
from lrfcal.estimate.minima import other_minimum
from lrfcal.estimate.problem import OnPlanes, marker_problem
from lrfcal.estimate.request import MarkerRequest, SolveOptions
from lrfcal.estimate.systematics import ModelError, Systematics
from lrfcal.model.marker import MarkerSensor, crossings
from lrfcal.model.motor import Clock
from lrfcal.model.unknowns import pack
from lrfcal.result import CalibrationResult, MarkerEvidence, Matched, Observer
from lrfcal.stages import alternatives, detection, joint, mds, refinement, timing
from lrfcal.stages.alternatives import Direction, Matching, Mirrored, Start, Turned
from lrfcal.stages.marker_sets import (
    AllPlanes,
    Chosen,
    FromStart,
    Joint,
    MarkerSets,
    Once,
    Refit,
    Settled,
    Stood,
)
from lrfcal.stages.propose import Proposal
from lrfcal.types import Detections, Fit, JointStates, MarkerMap, Noted, Observations, Recording, Solution, Tried


@dataclass(frozen=True)
class Observed:
    """The marker way's observations: the marker map, the blobs, every blob's returns with their motor angles, the
    sweep's passes (per scan), whether the clock offset is estimated, and what the directions' starts are matched
    from (lrfcal.stages.alternatives.Matching)."""

    markers: MarkerMap
    detections: Detections
    returns: Observations
    passes: np.ndarray
    estimate_clock: bool
    matching: Matching
    notes: tuple[str, ...] = ()  # what observing them noted (the clock offset held)


class RefineConfig(joint.JointConfig, Protocol):
    """What the marker way's refinement reads (lrfcal.stages.refinement): the joint solve's options
    (lrfcal.stages.joint.JointConfig) and the chi-square limit of the scales' score tests."""

    @property
    def max_reduced_chi2(self) -> float: ...


class MarkerWay:
    """Calibration with markers as the steps of lrfcal.pipeline's loop (a ``Way[Observed, alternatives.Start,
    MarkerSets]``): observe (stages 1-4: the marker map, the marker returns, their times, the association's search
    decided), the sets at each candidate start and their problem (4.-6.: servo direction, handedness, DH
    representative), the sets chosen again at each estimate (a start's: scales freed, blobs left out; after the
    choice: jointly with the surfaces, scales the data contradict, blobs the marker-only fit could not judge), the
    turning systematic, the paper's baseline beside, the checks: a result without clouds (lrfcal.pipeline adds them).
    Raises CalibrationError: no marker returns, no match, or the layout does not determine the DH parameters."""

    STAGES: ClassVar[tuple[str, ...]] = ()  # set below the module's STAGES
    NOTES: ClassVar[tuple[str, ...]] = ()  # what every calibration with markers notes first: nothing
    SEARCH: ClassVar[bool] = False  # its starts need no DH search's proposal

    def __init__(self, recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch,
                 observer: Observer) -> None:
        self.recording, self.joints, self.config, self.clock, self.observer = recording, joints, config, clock, observer
        nominal = recording.nominal
        assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        self.sensor = MarkerSensor.of("sphere", nominal.marker_radius_m, nominal.beam_divergence_rad,
                                      config.range_sigma_m)

    def observe(self, proposal: Proposal | None) -> tuple[Observed, list[Start]]:
        """Stages 1-4: the marker map, the blobs, the marker returns with their motor angles, whether the DH search
        matches them (``proposal``: none is asked for); the first start, the declared direction of the servo."""
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
        matching = alternatives.matching_of(returns, detections, markers, recording.nominal, config)  # 4.
        clock.lap("association")  # from the nominal DH; the DH search, when needed, counts with the solve
        return Observed(markers, detections, returns, passes, bool(estimate_clock), matching, held), [Direction(1)]

    def sets_at(self, observed: Observed, start: Start) -> MarkerSets:
        """5.: the marker-only sets at a candidate start (lrfcal.stages.alternatives)."""
        match start:
            case Direction():
                return alternatives.direction_sets(observed.matching, start,
                                                   self.joints if observed.estimate_clock else None,
                                                   self.recording.nominal, self.config, self.sensor)
            case Mirrored():
                return alternatives.mirrored_sets(start)
            case Turned():
                return alternatives.turned_sets(start)
        raise AssertionError(start)

    def problem(self, observed: Observed, sets: MarkerSets) -> MarkerRequest:
        """What to estimate on ``sets``: the marker returns (with the surfaces' returns in a joint solve), from the
        sets' start, the unknowns their alternative found the data need estimated."""
        alt, step = sets.alt, sets.step
        matched, surfaces, range_bias = alt.matched, None, False
        scores: tuple[str, ...] = ()
        match step:
            case FromStart():
                scores = tuple(joint.SCALES)  # the scales' score tests read its solution
            case Joint() | AllPlanes():
                assert step.rounds.found.returns is not None
                matched, range_bias, scores = step.rounds.matched, step.range_bias, tuple(joint.SCALES)
                surfaces = OnPlanes(step.rounds.found.returns, list(step.rounds.found.surfaces))
            case Refit(after=after) if after is not None:
                matched = after.matched
            case Once() | Refit():
                pass
            case _:
                raise AssertionError(f"nothing to solve at {step}")
        return MarkerRequest(matched, alt.markers, sets.origin, self.sensor, surfaces, Clock(alt.clock, sets.tau),
                             SolveOptions(estimate=alt.estimate, estimate_range_bias=range_bias, held_scores=scores))

    def reselect(self, observed: Observed, fit: Fit[MarkerSets]) -> MarkerSets | Fit[MarkerSets] | None:
        """The sets chosen again at ``fit``'s estimate: a candidate start's (lrfcal.stages.alternatives.reselected),
        or after the choice the refinement's (lrfcal.stages.refinement)."""
        if isinstance(fit.sets.step, FromStart | Once | Stood):
            return alternatives.reselected(fit, self.config)
        recorded = joint.Recorded(self.recording, self.joints.signed(fit.sets.alt.sign), observed.detections)
        return refinement.refined(refinement.Context(self.config, self.config.max_reduced_chi2, recorded), fit)

    def choose(self, observed: Observed, tried: Sequence[Tried[Start, MarkerSets]]
               ) -> Fit[MarkerSets] | list[Start]:
        """6.: the alternative chosen, or the further starts it needs (lrfcal.stages.alternatives.chosen)."""
        chosen = alternatives.chosen(tried, self.recording.nominal.dh, self.config)
        if not isinstance(chosen, Fit):
            return chosen
        alt = chosen.sets.alt
        self.clock.lap("solve")
        self.observer.matched(Matched(self.recording.scans, observed.detections, alt.assoc, alt.markers))
        return Fit(replace(chosen.sets, step=Chosen()), chosen.solution)

    def systematics(self, observed: Observed, best: Fit[MarkerSets]) -> Systematics:
        """The turning systematic: where the sweep turns on a marker (lrfcal.model.marker.crossings), the marker-only
        problem solved with only the in-plane part of those crossings' lateral residual. The lines of a turning
        crossing crowd about the turning point and bias the part across the scan plane; the variant leaves that part
        out and loses its information, so neither is right alone, and their difference is a model error the noise's
        sigma does not hold (docs/study.md, "A crossing that turns on its marker"). None where no crossing turns."""
        if self.config.surfaces:
            self.clock.lap("surfaces")
        alt, sol = best.sets.alt, best.sets.refined.marker_only
        pb, _ = marker_problem(alt.matched, alt.markers.positions_W, self.sensor)
        th, R_ref = pack(sol.params, sol.clock_offset_s)
        assert pb.markers is not None  # a problem of marker returns
        if not np.any(crossings(th, pb.markers, R_ref, alt.clock)[1]):
            return Systematics()
        variant = replace(self._marker_only(best), options=SolveOptions(estimate=alt.estimate, in_plane_at_turns=True))
        return Systematics(model_errors=(ModelError(
            "crossings of the sweep turn on some markers: the DH with only the in-plane part of their lateral residual",
            variant, sol),))

    def beside(self, observed: Observed, best: Fit[MarkerSets]) -> Mapping[str, MarkerRequest]:
        """The paper's method beside ours (``config.baseline``): the blob's brightest beam, the motor angle at the
        scan's stamp, point-to-centre residuals, on the same detections and association, the motor angles at the
        clock offset's start."""
        if not self.config.baseline:
            return {}
        alt = best.sets.alt
        peaks = alt.matched.subset(alt.matched.is_peak)
        lambda_scan = timing.scan_angles(self.recording.scans, self.joints.signed(alt.sign),
                                         clock_offset_s=self.config.clock_offset_s)
        peaks = alternatives.replace_arrays(peaks, lambda_rad=lambda_scan[peaks.scan])
        return {BASELINE: MarkerRequest(peaks, alt.markers, alt.start, self.sensor,
                                        options=SolveOptions(estimate=alt.estimate)).paper()}

    def checks(self, observed: Observed, best: Fit[MarkerSets], widened: Noted[Solution],
               beside: Mapping[str, Solution | CalibrationError]) -> CalibrationResult:
        """The checks of the estimate as solved (the systematics widen the result's covariance beside them), the
        other minimum, the paper's baseline: the result without clouds."""
        config, nominal, sets = self.config, self.recording.nominal, best.sets
        assert isinstance(sets.step, Settled)
        alt, marker_only, found = sets.alt, sets.refined.marker_only, sets.step.joint.found
        request = self._marker_only(best)
        checks = marker_checks(best.solution, marker_only, request, observed.passes, config, nominal.dh)
        checks.append(other_minimum(marker_only, request, nominal, config))
        baseline: Noted[Solution | None] = Noted(None)
        if BASELINE in beside:
            paper = beside[BASELINE]
            baseline = (Noted(paper) if isinstance(paper, Solution)
                        else Noted(None, (f"the paper's method could not be run: {paper}",)))
            self.clock.lap("baseline")
        evidence = MarkerEvidence(markers=alt.markers, detections=observed.detections, observations=alt.matched,
                                  association=alt.assoc, baseline=baseline.value, surfaces=found.surfaces,
                                  surface_returns=found.returns)
        ours = widened.value
        return CalibrationResult(
            recording=self.recording, evidence=evidence, start=alt.start, solution=ours, checks=tuple(checks),
            servo_sign=alt.sign, notes=(*observed.notes, *alt.notes, *widened.notes, *baseline.notes),
            side_by_side={"markers only": marker_only,
                          "markers and every plane" if config.all_planes else "markers and their surfaces": ours},
        )

    def _marker_only(self, best: Fit[MarkerSets]) -> MarkerRequest:
        """The marker-only problem of the chosen alternative as it ends up, from its marker-only solution."""
        alt, sol = best.sets.alt, best.sets.refined.marker_only
        return MarkerRequest(alt.matched, alt.markers, sol.params, self.sensor,
                             clock=Clock(alt.clock, sol.clock_offset_s), options=SolveOptions(estimate=alt.estimate))


#: the paper's method, beside ours
BASELINE = "the paper's method"

#: The stages of a calibration with markers in the order they run, as reported to ``progress`` and in
#: CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("mds", "detection", "timing", "association", "solve", "surfaces", "baseline",
                           "reprojection", "geometry")


MarkerWay.STAGES = STAGES

__all__ = ["BASELINE", "STAGES", "MarkerWay", "Observed", "RefineConfig"]
