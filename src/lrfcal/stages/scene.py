"""Targetless calibration as the steps of lrfcal.pipeline's orchestrator (the plane way; lrfcal.stages.targetless
holds its segmentation and its one cost): observe (the sampled returns, the planes segmented once at the rig file's
DH, what the scene determines), starts (the solve every start shares: the held parameters, the prior, the clock),
refine (the cost minimised from the rig file's DH and from every other start the data allow, the lowest minimum
kept: lrfcal.stages.starts), checks.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
from numpy.typing import NDArray

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability, solve
from lrfcal.estimate.checks import CheckConfig, plane_checks
from lrfcal.estimate.information import plane_information
from lrfcal.model.kinematics import DH, Params, points_M
from lrfcal.model.motor import MotorClock
from lrfcal.model.unknowns import CORE_NAMES
from lrfcal.result import CalibrationResult, PlaneEvidence, PlaneFit
from lrfcal.stages import holdout, planes, propose, starts, timing
from lrfcal.stages.sampling import hash_sample
from lrfcal.stages.targetless import (
    BENDING_M,
    DH_NAMES,
    MOTOR_FRAME,
    SEGMENT_SAMPLES,
    STAGES,
    Beams,
    Segmented,
    Start,
    fixed_solve,
    sample_returns,
)
from lrfcal.types import Check, JointStates, Noted, Recording, Solution, SurfaceReturns

FloatArray = NDArray[np.float64]
#: what runs ahead of the plane way: the DH search's proposal, asked for by the check "starts agree"
#: (lrfcal.stages.propose.proposal_ahead; valid while the way's ``ahead`` context lasts)
Proposal = Callable[[], propose.DHProposal]


@dataclass(frozen=True)
class Scene:
    """The plane way's observations: the sampled returns ``beams`` and the held-out scans' ``held_beams``, the
    segmentation's sample ``seg``, the start's segmentation, what is held (and why) and whether the clock offset is
    estimated, the motor clock, the sweep's passes, the design drawing's prior on the DH, the first round's planes'
    thickness and the DH search running ahead (:data:`Proposal`)."""

    beams: Beams
    held_beams: Beams
    seg: NDArray[np.int64]
    segmented: Segmented
    held: tuple[str, ...]
    held_reason: str
    estimate_clock: bool
    motor: MotorClock
    passes: NDArray[np.int64]
    prior: tuple[FloatArray, FloatArray]
    first_thickness_m: float
    proposal: Proposal
    #: what the plane way noted so far, in order (the scene's: the clock offset held, the parameters held; then the
    #: refinement's, :meth:`PlaneWay.refine`)
    notes: tuple[str, ...] = ()


#: the starts step's outcome: the observations and the one cost's solve from a start ((dh, tau) -> its minimum)
Started = tuple[Scene, Callable[[DH, float], Solution]]
#: the refine step's outcome: the observations and the lowest minimum with the check "starts agree"
Refined = tuple[Scene, starts.Minima]


class PlaneWay:
    """The targetless way (module docstring) on ``recording`` (its scans those the joint states cover; its markers,
    if any, ignored): a result without clouds (lrfcal.pipeline adds them).
    Raises CalibrationError: the scene shows no plane, or determines no DH parameter."""

    STAGES = STAGES

    #: what every targetless calibration notes first (before the orchestrator's notes on the scans)
    NOTES = ("targetless: the DH parameters from the flatness of the scene's planes; without markers there is no world "
             "frame, so the mount pose is not estimated (frame M)",)

    def __init__(self, recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch) -> None:
        self.recording, self.joints, self.config, self.clock = recording, joints, config, clock

    @contextlib.contextmanager
    def ahead(self) -> Iterator[Proposal]:
        """The DH search for the check "starts agree" in forked children meanwhile (its starts do not depend on the
        fit; ended at once if the fit is refused): its proposal, when asked for."""
        with propose.proposal_ahead(self.recording.scans, self.joints) as proposal:
            yield proposal

    def observe(self, ahead: Proposal) -> Scene:
        """Stages 1-3: the returns sampled, segmented at the start; what the scene determines, the rest held
        (``ahead``: the DH search's proposal, kept for the check "starts agree")."""
        config, clock, joints = self.config, self.clock, self.joints
        assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        notes: list[str] = []
        scans, nominal, tau0 = self.recording.scans, self.recording.nominal, config.clock_offset_s
        motor = MotorClock.from_joints(joints)
        passes = timing.sweep_passes(timing.scan_angles(scans, joints, clock_offset_s=tau0))
        estimate_clock = (passes.max() >= 1) if config.estimate_clock is None else config.estimate_clock
        # every 5th scan is held out of the fit: the calibration must not make those scans' planes thicker (holdout)
        hold = np.broadcast_to(holdout.held_out_scans(scans.stamps_s.size)[:, None], scans.ranges_m.shape)
        beams = sample_returns(scans, config.plane_returns, skip=hold)
        held_beams = sample_returns(scans, holdout.HOLDOUT_RETURNS, skip=~hold)
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
                                                             clock_offset_s=tau0))
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
        return Scene(beams, held_beams, seg, segmented, held, held_reason, estimate_clock, motor,
                     passes, prior, start.thickness_m, ahead, tuple(notes))

    def starts(self, scene: Scene) -> Started:
        """The solve every start shares (the rig file's DH, the DH search's proposal and agreeing starts: refine):
        the one cost over the fixed planes, the held parameters, the prior, the clock."""
        assert self.config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
        footing = Start.of(self.recording.nominal.dh, 0.0, self.config).footing(self.config)
        solve_at = partial(solve.solve_planes, range_sigma_m=self.config.range_sigma_m,
                           clock=scene.motor if scene.estimate_clock else None, hold=scene.held,
                           dh_prior=scene.prior, options=solve.PlaneOptions(footing=footing))
        return scene, partial(fixed_solve, solve_at, scene.segmented)

    def refine(self, started: Started) -> Refined:
        """Stage 4: the cost minimised from the rig file's DH and from the other starts the data allow, the lowest
        minimum kept (lrfcal.stages.starts); the held parameters' uncertainty added to its covariance."""
        (scene, fit), config, tau0 = started, self.config, self.config.clock_offset_s
        first = fit(self.recording.nominal.dh, tau0)
        cost = starts.Cost(scene.segmented, scene.motor, float(config.range_sigma_m or 0.0), scene.prior)
        found = starts.lowest_minimum(first, fit, cost, scene.held, self.recording.nominal.dh, tau0, scene.proposal)
        self.clock.lap("starts")
        if not scene.estimate_clock and scene.passes.max() < 1 or config.estimate_clock is False:
            scene = replace(scene, notes=(*scene.notes, f"clock offset held at {tau0 * 1000:+.1f} ms (not estimated: "
                                          + ("a one-way sweep does not separate it)" if config.estimate_clock is None
                                             else "as asked)")))
        if found.start != "the rig file's DH":
            scene = replace(scene, notes=(*scene.notes, f"the estimate is the minimum reached from {found.start}: it "
                                          "fits the scene's planes better than the one from the rig file's DH"))
        counted = scene.segmented.returns
        if found.solution.inlier is not None:  # the returns that count at the estimate
            counted = counted.subset(found.solution.inlier)
        sol = _consider(found.solution, counted, scene.motor if scene.estimate_clock else None, scene.held, config,
                        scene.prior)
        self.clock.lap("solve")
        return scene, replace(found, solution=sol)

    def checks(self, refined: Refined, shared: Callable[[Solution], Check]) -> CalibrationResult:
        """Stage 5: the checks (``shared``: those of both ways, first), "starts agree", the held-out planes, the
        flatness before and after."""
        (scene, found), config, clock = refined, self.config, self.clock
        sol, segmented = found.solution, scene.segmented
        returns, planes_found = segmented.returns, segmented.planes
        labels = segmented.labels.copy()  # the returns that count at the estimate (its cut, incidence, edges)
        if sol.inlier is not None:
            labels[labels >= 0] = np.where(sol.inlier, labels[labels >= 0], -1)
        nominal, tau0, beams, motor = self.recording.nominal, config.clock_offset_s, scene.beams, scene.motor
        checks = [found.check, *plane_checks(sol, returns, scene.passes, scene.held, config, scene.prior,
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
                             np.bincount(labels[labels >= 0], minlength=len(planes_found)), scene.held,
                             scene.held_reason, found.start, n_before, n_after)
        evidence = PlaneEvidence(plane_fit=plane_fit, returns=returns)
        return CalibrationResult(recording=self.recording, evidence=evidence, start=Params(MOTOR_FRAME, nominal.dh),
                                 solution=sol, checks=(shared(sol), *checks), notes=scene.notes)


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


def _held_reason(held: tuple[str, ...]) -> str:
    """Why the DH parameters ``held`` are held ("" when none)."""
    if not held:
        return ""
    return (f"the scene's planes do not determine {', '.join(held)} (1-sigma beyond "
            f"{observability.LIMITS['a'] * 1000:g} mm / {math.degrees(observability.LIMITS['alpha']):g}"
            f" deg, judged at the start): held at the nominal value, not estimated")


def _consider(sol: Solution, returns: SurfaceReturns, motor: MotorClock | None, held: tuple[str, ...],
              config: CheckConfig, prior: tuple[FloatArray, FloatArray]) -> Solution:
    """Carry the held parameters' uncertainty (CalibConfig.nominal_tolerance, the design drawing's) into the
    estimated ones: cov_e += S C_h S^T, S = -I_ee^-1 I_eh (the sensitivity of the estimate to the held value)."""
    if not held:
        return sol
    assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    info, names = plane_information(returns, sol.params, range_sigma_m=config.range_sigma_m, clock=motor,
                                          clock_offset_s=sol.clock_offset_s, dh_prior=prior)
    info = info / max(sol.reduced_chi2, 1.0)
    est = [i for i, n in enumerate(names) if n not in held]
    hid = [names.index(n) for n in held]
    S = -np.linalg.solve(info[np.ix_(est, est)], info[np.ix_(est, hid)])
    tol = dict(zip(DH_NAMES, config.nominal_tolerance, strict=True))
    extra = S @ np.diag([tol[n] ** 2 for n in held]) @ S.T
    cov = sol.covariance.copy()
    pos = {n: CORE_NAMES.index(n) for n in names}
    for i, a in enumerate(est):
        for j, b in enumerate(est):
            ia, ib = pos[names[a]], pos[names[b]]
            if ia < 10 and ib < 10:
                cov[ia, ib] += extra[i, j]
    return replace(sol, covariance=cov, sigma=np.sqrt(np.clip(np.diag(cov), 0.0, None)))


__all__ = ["PlaneWay", "Proposal", "Refined", "Scene", "Started"]
