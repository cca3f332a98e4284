"""Targetless calibration as the steps of lrfcal.pipeline's loop (the plane way; lrfcal.stages.targetless holds its
segmentation and its one cost): observe (the sampled returns, the planes segmented once at the rig file's DH, what
the scene determines), the cost minimised from the rig file's DH and then from every other start the data allow (the
DH search's proposal and agreeing starts), the lowest minimum chosen (lrfcal.stages.starts), nothing chosen again (the
assignment is fixed by design), the held parameters' uncertainty carried into the covariance, the checks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.errors import CalibrationError, RunOffError
from lrfcal.estimate import observability
from lrfcal.estimate.checks import dh_text, plane_checks
from lrfcal.estimate.information import plane_information
from lrfcal.estimate.request import PlaneRequest
from lrfcal.estimate.systematics import Considered, Systematics, widened
from lrfcal.model.kinematics import Params, points_M
from lrfcal.model.motor import MotorClock
from lrfcal.model.range_pattern import WIDTH_BEAMS
from lrfcal.result import CalibrationResult, Observer, PlaneEvidence, PlaneFit
from lrfcal.stages import holdout, planes, propose, starts, timing
from lrfcal.stages.sampling import hash_sample
from lrfcal.stages.starts import NOMINAL, PlaneSets, PlaneStart
from lrfcal.stages.targetless import (
    BENDING_M,
    DH_NAMES,
    MOTOR_FRAME,
    SEGMENT_SAMPLES,
    STAGES,
    Beams,
    OneCost,
    Segmented,
    Start,
    mixed_pixels,
    own_returns,
    sample_returns,
)
from lrfcal.types import Check, Fit, JointStates, Noted, Recording, Solution, SurfaceReturns, Tried

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Scene:
    """The plane way's observations: the sampled returns ``beams`` and the held-out scans' ``held_beams``, the
    segmentation's sample ``seg``, the start's segmentation, what is held (and why) and whether the clock offset is
    estimated, the motor clock, the sweep's passes, the one cost every start minimises (its held parameters, prior,
    clock and footing), the first round's planes' thickness and the DH search's proposal (None: not searched)."""

    beams: Beams
    held_beams: Beams
    seg: NDArray[np.int64]
    segmented: Segmented
    held: tuple[str, ...]
    held_reason: str
    estimate_clock: bool
    motor: MotorClock
    passes: NDArray[np.int64]
    cost: OneCost
    first_thickness_m: float
    proposal: propose.Proposal | None
    #: what the plane way noted observing the scene, in order (the clock offset held, the parameters held)
    notes: tuple[str, ...] = ()


class PlaneWay:
    """The targetless way (module docstring) on ``recording`` (its scans those the joint states cover; its markers,
    if any, ignored), a ``Way[Scene, PlaneStart, PlaneSets]``: a result without clouds (lrfcal.pipeline adds them).
    Raises CalibrationError: the scene shows no plane, or determines no DH parameter."""

    STAGES: ClassVar[tuple[str, ...]] = STAGES

    #: what every targetless calibration notes first (before the orchestrator's notes on the scans)
    NOTES: ClassVar[tuple[str, ...]] = (
        "targetless: the DH parameters from the flatness of the scene's planes; without markers there is no world "
        "frame, so the mount pose is not estimated (frame M)",)
    SEARCH: ClassVar[bool] = True  # its other starts are the DH search's proposal and agreeing starts

    def __init__(self, recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch,
                 observer: Observer) -> None:
        self.recording, self.joints, self.config, self.clock = recording, joints, config, clock
        #: the held parameters' consider covariance of each estimate judged (reselect) by its solution's id, with
        #: the solution and what was held: the one kept is widened by the same, not computed again
        self._considered: dict[int, tuple[Solution, tuple[str, ...], Systematics]] = {}

    def observe(self, proposal: propose.Proposal | None) -> tuple[Scene, list[PlaneStart]]:
        """Stages 1-3: the returns sampled, segmented at the start; what the scene determines, the rest held
        (``proposal``: the DH search's, for the other starts); the first start, the rig file's DH."""
        config, clock, joints = self.config, self.clock, self.joints
        assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        notes: list[str] = []
        scans, nominal, tau0 = self.recording.scans, self.recording.nominal, config.clock_offset_s
        motor = MotorClock.from_joints(joints)
        passes = timing.sweep_passes(timing.scan_angles(scans, joints, clock_offset_s=tau0))
        estimate_clock = (passes.max() >= 1) if config.estimate_clock is None else config.estimate_clock
        # every 5th scan is held out of the fit: the calibration must not make those scans' planes thicker (holdout)
        hold = np.broadcast_to(holdout.held_out_scans(scans.stamps_s.size)[:, None], scans.ranges_m.shape)
        # neither the fit nor the held-out planes take the returns beside a jump edge (mixed pixels)
        mixed = mixed_pixels(scans, joints, tau0, config.range_sigma_m)
        mixed |= own_returns(scans, joints, tau0, nominal.dh, nominal.self_boxes)  # the rig's own parts: no scene
        beams = sample_returns(scans, config.plane_returns, skip=hold | mixed)
        held_beams = sample_returns(scans, holdout.HOLDOUT_RETURNS, skip=~hold | mixed)
        seg = hash_sample(beams.scan, beams.beam, SEGMENT_SAMPLES)  # the sample's first, in hash order
        clock.lap("timing")

        prior = (nominal.dh.vector(), np.array(config.nominal_tolerance, dtype=float))
        start = Start.of(nominal.dh, tau0, config, BENDING_M)
        segmented = start.segment(beams, seg, motor, config)  # once: the assignment the cost keeps (targetless)
        returns, found = segmented.returns, segmented.planes
        clock.lap("planes")
        _check_scene(found, returns)
        # what the scene determines, judged at the start: one information, each judgement takes its part of it
        scene = observability.Information(*plane_information(returns, Params(MOTOR_FRAME, start.dh),
                                                             range_sigma_m=config.range_sigma_m, clock=motor,
                                                             clock_offset_s=tau0,
                                                             range_pattern=config.range_pattern))
        if estimate_clock:
            determined = _clock_determined(scene, tau0)
            estimate_clock = determined.value
            notes += determined.notes
        held = scene.undetermined_dh(() if estimate_clock else ("clock_offset",), prior[1])
        held_reason = _held_reason(held)
        if held_reason:
            notes.append(held_reason)
        if len(held) == len(DH_NAMES):
            raise CalibrationError(f"the scene does not determine any DH parameter: {held_reason}; add planes of other "
                                   "orientations (across the motor axis), or calibrate with markers")
        footing = Start.of(nominal.dh, 0.0, config).footing(config)
        cost = OneCost(config.range_sigma_m, motor if estimate_clock else None, held, prior, footing,
                       config.range_pattern)
        return (Scene(beams, held_beams, seg, segmented, held, held_reason, bool(estimate_clock), motor, passes, cost,
                      start.thickness_m, proposal, tuple(notes)), [PlaneStart(NOMINAL, nominal.dh)])

    def sets_at(self, scene: Scene, start: PlaneStart) -> PlaneSets:
        """The sets at a start: the scene's planes and returns, fixed; only where the cost is minimised from differs."""
        return PlaneSets(start)

    def problem(self, scene: Scene, sets: PlaneSets) -> PlaneRequest:
        """Stage 4: the one cost over the fixed planes from the start (lrfcal.stages.targetless.OneCost), the
        parameters the start holds beyond the scene's held too."""
        cost = scene.cost if not sets.start.held else replace(scene.cost, hold=(*scene.cost.hold, *sets.start.held))
        return cost.request(scene.segmented, sets.start.dh, self.config.clock_offset_s)

    def reselect(self, scene: Scene, fit: Fit[PlaneSets]) -> PlaneSets | Fit[PlaneSets] | None:
        """What the scene determines, judged again at the estimate: the planes and their returns are never chosen
        again (segmented once, at the start: the one cost cannot oscillate, lrfcal.stages.targetless), but an
        estimated DH parameter whose 1-sigma at the estimate is beyond its limit (lrfcal.estimate.observability's,
        the rule the start's judgement uses) is held at the nominal value, the farthest beyond first, and the cost
        minimised again with it held: the sets of a start from the estimate (None: every one within its limit, or
        holding one more would leave none estimated; the check "observability" then judges). The start's judgement
        takes the noise as independent; the estimate's sigma (as the check judges it: with the held parameters'
        tolerance carried in, :meth:`systematics`) counts its correlation along the scan (the per-scan sandwich),
        which can put a parameter just beyond its limit (the box replica's a: 5.2-6.2 mm against 5 mm, then b with
        a's tolerance: 5.3 mm). Each round holds one more parameter, so there are at most four."""
        held = _held(scene, fit.sets)
        stated = widened(fit.solution, self.systematics(scene, fit), []).value.sigma
        sigma = {n: float(stated[6 + DH_NAMES.index(n)]) for n in DH_NAMES if n not in held}
        beyond = observability.beyond_limits(sigma)
        if not beyond or len(sigma) == 1:
            return None
        nominal = self.recording.nominal.dh
        dh = replace(fit.solution.params.dh, **{beyond[0]: getattr(nominal, beyond[0])})
        return PlaneSets(PlaneStart(fit.sets.start.name, dh, (*fit.sets.start.held, beyond[0])))

    def choose(self, scene: Scene, tried: Sequence[Tried[PlaneStart, PlaneSets]]
               ) -> Fit[PlaneSets] | list[PlaneStart]:
        """The lowest minimum among the starts tried, with the check "starts agree" (lrfcal.stages.starts); after the
        rig file's DH, the other starts the DH search's proposal gives first."""
        first = tried[0].outcome
        if isinstance(first, RunOffError):  # what the data say: the planes do not hold the DH near the rig file's
            raise CalibrationError(
                f"convergence: the planes' cost, minimised from the rig file's DH ({dh_text(tried[0].start.dh)}), ran "
                f"off to where {first.counted} of its {first.returns} returns meet their plane within 4 sigma at a "
                "usable incidence: the scene's planes do not hold the DH near the rig file's values; check its dh "
                "against the drawings (lrfcal inspect BAG proposes them from the planes) or record a scene with more "
                "planes, seen at more motor angles") from None
        if not isinstance(first, Fit):
            raise first  # the rig file's DH: its failure is the calibration's (the search is not waited for)
        found = starts.searched(scene.proposal)
        if len(tried) == 1 and (more := starts.further(first.solution, found, scene.held, self.recording.nominal.dh)):
            return more
        cost = starts.Cost(scene.segmented, scene.motor, float(self.config.range_sigma_m or 0.0), scene.cost.prior)
        lowest = starts.lowest(tried, cost, scene.held, found)
        self.clock.lap("starts")
        # the start as its estimate stood (with what was held there, reselect)
        start = next(t.outcome.sets.start for t in tried
                     if isinstance(t.outcome, Fit) and t.outcome.solution is lowest.solution)
        return Fit(PlaneSets(start, lowest.check), lowest.solution)

    def systematics(self, scene: Scene, best: Fit[PlaneSets]) -> Systematics:
        """The held parameters' uncertainty (CalibConfig.nominal_tolerance, the design drawing's), carried into the
        estimated ones (a "consider" covariance, lrfcal.estimate.systematics), from the information at the estimate
        over the returns that count there."""
        held = _held(scene, best.sets)
        if not held:
            return Systematics()
        sol = best.solution
        known = self._considered.get(id(sol))
        if known is not None and known[0] is sol and known[1] == held:
            return known[2]
        assert self.config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        counted = scene.segmented.returns
        if sol.inlier is not None:  # the returns that count at the estimate
            counted = counted.subset(sol.inlier)
        info, names = plane_information(counted, sol.params, range_sigma_m=self.config.range_sigma_m,
                                        clock=scene.cost.clock, clock_offset_s=sol.clock_offset_s,
                                        dh_prior=scene.cost.prior, range_pattern=scene.cost.range_pattern)
        tol = dict(zip(DH_NAMES, self.config.nominal_tolerance, strict=True))
        out = Systematics(considered=Considered(info, names, {n: tol[n] for n in held}))
        self._considered[id(sol)] = (sol, held, out)
        return out

    def beside(self, scene: Scene, best: Fit[PlaneSets]) -> Mapping[str, PlaneRequest]:
        """No other method runs beside the targetless one."""
        return {}

    def checks(self, scene: Scene, best: Fit[PlaneSets], widened: Noted[Solution],
               beside: Mapping[str, Solution | CalibrationError]) -> CalibrationResult:
        """Stage 5: "starts agree" (the choice's), the checks of the widened estimate, the held-out planes, the
        flatness before and after; the notes: the scene's, the clock offset held, the start the estimate came from."""
        config, clock, tau0 = self.config, self.clock, self.config.clock_offset_s
        clock.lap("solve")
        notes = list(scene.notes)
        if not scene.estimate_clock and scene.passes.max() < 1 or config.estimate_clock is False:
            notes.append(f"clock offset held at {tau0 * 1000:+.1f} ms (not estimated: "
                         + ("a one-way sweep does not separate it)" if config.estimate_clock is None else "as asked)"))
        if config.range_pattern:
            notes.append("the scanner's range error along the scan estimated with the DH (a range offset per "
                         f"{WIDTH_BEAMS} beams, its slow part held: lrfcal.model.range_pattern), as the rig file "
                         "(range_pattern) or --range-pattern asks")
        if best.sets.start.name != NOMINAL:
            notes.append(f"the estimate is the minimum reached from {best.sets.start.name}: it fits the scene's planes "
                         "better than the one from the rig file's DH")
        sol, segmented = widened.value, scene.segmented
        returns, planes_found = segmented.returns, segmented.planes
        labels = segmented.labels.copy()  # the returns that count at the estimate (its cut, incidence, edges)
        if sol.inlier is not None:
            labels[labels >= 0] = np.where(sol.inlier, labels[labels >= 0], -1)
        nominal, beams, motor = self.recording.nominal, scene.beams, scene.motor
        assert best.sets.agree is not None  # the choice's verdict
        held, at_estimate = _held(scene, best.sets), _held_reason(best.sets.start.held, AT_ESTIMATE)
        if at_estimate:
            notes.append(at_estimate)
        checks = [best.sets.agree, *plane_checks(sol, returns, scene.passes, held, config, scene.cost.prior,
                                                 nominal.dh)]
        checks.append(_held_out_check(scene.held_beams, motor, Params(MOTOR_FRAME, nominal.dh), tau0, sol,
                                      scene.first_thickness_m))
        clock.lap("checks")
        lam_b = motor.angles(beams.times_s, tau0)[0]
        lam_a = motor.angles(beams.times_s, sol.clock_offset_s)[0]
        before, n_before = planes.flatness(points_M(beams.ranges_m, lam_b, beams.mu_rad, nominal.dh), labels,
                                           len(planes_found))
        after, n_after = planes.flatness(points_M(beams.ranges_m, lam_a, beams.mu_rad, sol.params.dh), labels,
                                         len(planes_found))
        plane_fit = PlaneFit(tuple(planes_found), before, after,
                             np.bincount(labels[labels >= 0], minlength=len(planes_found)), held,
                             "; ".join(n for n in (scene.held_reason, at_estimate) if n), best.sets.start.name,
                             n_before, n_after)
        evidence = PlaneEvidence(plane_fit=plane_fit, returns=returns)
        return CalibrationResult(recording=self.recording, evidence=evidence, start=Params(MOTOR_FRAME, nominal.dh),
                                 solution=sol, checks=tuple(checks), notes=(*notes, *widened.notes))


def _held_out_check(held: Beams, motor: MotorClock, start: Params, tau0: float, sol: Solution,
                    thickness_m: float) -> Check:
    """The held-out scans' planes with the start and with the calibrated parameters (lrfcal.stages.holdout), segmented
    with the first round's ``thickness_m``."""
    clouds = [points_M(held.ranges_m, motor.angles(held.times_s, tau)[0], held.mu_rad, dh)
              for dh, tau in ((start.dh, tau0), (sol.params.dh, sol.clock_offset_s))]
    result = holdout.held_out_flatness(clouds[0], clouds[1], thickness_m)
    return Check("held-out planes", result.passed, result.detail())


def _check_scene(found: list[planes.ScenePlane], returns: SurfaceReturns) -> None:
    if not found:
        raise CalibrationError(
            "targetless: the scene shows no plane with enough returns (at least 100 within the incidence limit): "
            "calibrate in a room or with markers")


def _clock_determined(scene: observability.Information, tau: float) -> Noted[bool]:
    """Whether the scene determines the clock offset (1-sigma within its limit, judged at the start, without the
    design drawing's prior); when not, a note says it is held."""
    sigma = scene.sigma("clock_offset")
    limit = observability.LIMITS["clock_offset"]
    if sigma <= limit:
        return Noted(True)
    return Noted(False, (f"clock offset held at {tau * 1000:+.1f} ms: the scene's planes determine it only to "
                         f"{sigma * 1000:.3g} ms (limit {limit * 1000:g} ms)",))


def _held(scene: Scene, sets: PlaneSets) -> tuple[str, ...]:
    """The DH parameters held at the nominal: those the start's information does not determine, then those held at
    an estimate (PlaneWay.reselect)."""
    return (*scene.held, *sets.start.held)


#: where the parameters held beyond the start's were judged (PlaneWay.reselect)
AT_ESTIMATE = "judged at the estimate, whose sigma counts the noise's correlation along the scan"


def _held_reason(held: tuple[str, ...], where: str = "judged at the start") -> str:
    """Why the DH parameters ``held`` are held ("" when none), judged ``where``."""
    if not held:
        return ""
    return (f"the scene's planes do not determine {', '.join(held)} (1-sigma beyond "
            f"{observability.LIMITS['a'] * 1000:g} mm / {math.degrees(observability.LIMITS['alpha']):g}"
            f" deg, {where}): held at the nominal value, not estimated")


__all__ = ["PlaneWay", "Scene"]
