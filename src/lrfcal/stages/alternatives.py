"""The marker way's start (lrfcal.stages.markers.MarkerWay.starts, stages 4-6): the discrete alternatives a
marker-only solve can start from, and the one chosen. For each direction of the servo (the data cannot tell them
apart): the blobs matched to the marker map (lrfcal.stages.matching, from the nominal DH or the DH search's
candidates), the start (mount pose from that alignment, DH from the nominal), the observability judged there, and
the marker-only solve, with the blobs that disagree with the map left out; then the direction chosen
(lrfcal.estimate.checks.servo_direction), the map's other handedness where the nominal DH prefer it, and the DH
representative nearer the nominal.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np

from lrfcal.config import Stopwatch
from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability, solve
from lrfcal.estimate.checks import CheckConfig, far_from_nominal, mirror_check, nearer_mirror, servo_direction
from lrfcal.estimate.information import information_at
from lrfcal.model.kinematics import DH, Params, Pose, dh_twins, homogeneous
from lrfcal.model.motor import Clock, MotorClock
from lrfcal.stages import association, joint, matching, start
from lrfcal.types import Association, Detections, JointStates, MarkerMap, Nominal, Observations, Solution


class AlternativesConfig(CheckConfig, matching.MatchConfig, Protocol):
    """The configuration the start reads: its slice of lrfcal.config.CalibConfig (which satisfies it): the checks'
    (the nominal tolerance, the chi-square limit, the range noise), the matching's and the clock's start."""

    @property
    def clock_offset_s(self) -> float: ...


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
    notes: tuple[str, ...] = ()  # what its start noted (MarkerWay.refine: then what its refinement noted)
    estimate: tuple[str, ...] = ()  # the unknowns held by default that its solves estimate (SCALES found off)
    #: a disagreement with the marker map (in words) that the marker-only fit found but could not judge, as it does
    #: not determine the DH parameters (one scan line per marker): judged at the joint solution (_judged_jointly)
    unjudged: str = ""


def in_nominal_representative(chosen: Alternative, nominal: DH, fit: solve.Solver) -> Alternative:
    """The marker-only solution in the DH representative nearer the nominal DH: solved again from its turned twin
    (-a, -alpha, b, beta + pi with the mount turned by pi about the motor axis: the same rig, lrfcal.model.kinematics.
    dh_twins) when that twin is nearer. A solve from the mirror image (:func:`handedness`) or from a coarse start
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


def handedness(chosen: Alternative, nominal: DH, config: AlternativesConfig, fit: solve.Solver) -> Alternative:
    """The marker-only solution in the marker map's other handedness, when the nominal DH prefer it.

    Tape distances fix the map only up to a reflection. With the map mirrored, the estimate's mirror twin
    (lrfcal.estimate.checks.nearer_mirror) explains the data exactly as well, its mount F T_W_M Q (F the map's
    reflection,
    Q the twin's isometry in M). Near a scan plane perpendicular to the motor axis the association cannot tell the
    handedness, so it is chosen here by the nominal DH: solved again from that twin. The result must then pass the
    mirror check; otherwise the first solution stays (and the check refuses it)."""
    found = nearer_mirror(chosen.solution.params.dh, nominal, config, chosen.solution.sigma[6:10])
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
    if not mirror_check(sol.params.dh, nominal, config, sol.sigma[6:10]).passed:
        return chosen
    note = (f"the marker map matched in the other handedness: its mirror image ({name}) is {d_twin:.1f} nominal "
            f"tolerances from the nominal DH, the first estimate {d_est:.1f}; solved again in the map's mirror image")
    assoc = replace(chosen.assoc, mirrored=not chosen.assoc.mirrored, T_W_M=T)
    return replace(chosen, markers=markers, assoc=assoc, solution=sol, notes=(*chosen.notes, note))


def servo_alternatives(returns: Observations, detections: Detections, markers: MarkerMap,
                        joints: JointStates | None, nominal: Nominal, config: AlternativesConfig, fit: solve.Solver,
                        clock: Stopwatch) -> Alternative:
    """4.-6.: association and marker-only solve for each direction of the servo (the data cannot tell them apart),
    and the direction chosen; ``joints``: the joint states the clock offset is estimated by (None: held). The DH
    search (lrfcal.stages.start) runs only when neither direction associates well from the nominal values."""
    signed = {sign: returns if sign > 0 else replace_arrays(returns, lambda_rad=-returns.lambda_rad)
              for sign in (1, -1)}
    first: dict[int, Association | None] = {}

    def associated(sign: int) -> Association | None:  # from the nominal DH, once, when first needed
        if sign not in first:
            first[sign] = matching.associate_nominal(signed[sign], detections, markers, nominal, config)
        return first[sign]

    # the DH search runs when neither direction associates well (the other is associated only if the declared fails)
    search = not any((a := associated(s)) is not None and matching.good(a, signed[s], config) for s in (1, -1))
    clock.lap("association")  # from the nominal DH; the DH search, when needed, counts with the solve
    alternatives: list[Alternative] = []
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


def _marker_solution(
    sign: int, start_dh: DH, assoc: Association | None, markers: MarkerMap, returns: Observations,
    joints: JointStates | None, config: AlternativesConfig, fit: solve.Solver,
) -> Alternative:
    """Start, observability check and marker-only solve for one direction of the servo (``returns`` with their
    motor angles already signed), from the association made with ``start_dh``; ``joints``: the joint states the
    clock offset is estimated by (None: held).

    Raises CalibrationError when the blobs could not be matched, when the data do not determine the DH parameters
    (judged at the start, before any solver runs), or when blobs disagree with the marker map beyond repair.
    """
    assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    if assoc is None:
        raise _NoMatch("association: no alignment of the blobs with the marker map (check the tape "
                               "distances' file and unit, and the marker radius)")
    if assoc.mirrored:
        markers = association.unmirror(markers)
    matched = with_markers(returns, assoc.blob_to_marker)
    n_matched = len(np.unique(matched.marker))
    if n_matched < 4:
        raise _NoMatch(
            f"only {n_matched} markers matched to detections (need >= 4); alignment RMS {assoc.rms_m * 1000:.1f} mm"
        )
    start = Params(Pose.from_matrix(assoc.T_W_M), start_dh)  # 5.
    motor = None if joints is None else MotorClock.from_joints(joints if sign > 0 else negated(joints))
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
    while off := joint.most_off(sol, config.max_reduced_chi2):  # before any marker is judged moved: a range scale
        notes += off.notes                                      # moves every far marker from its tape position
        estimate = (*estimate, off.value)
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
        assoc, matched = without_blobs(assoc, matched, bad, why)
        sol = fit(matched, markers, sol.params, clock=Clock(motor, sol.clock_offset_s))
    return Alternative(sign, markers, assoc, matched, start, motor, sol, tuple(notes), estimate)


def negated(joints: JointStates) -> JointStates:
    return JointStates(stamps_s=joints.stamps_s, positions_rad=-joints.positions_rad, name=joints.name)


def without_blobs(assoc: Association, matched: Observations, bad: np.ndarray, why: str
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


def with_markers(returns: Observations, blob_to_marker: np.ndarray) -> Observations:
    """Label every return with its blob's marker and keep the labelled ones."""
    labelled = replace_arrays(returns, marker=np.asarray(blob_to_marker)[returns.blob])
    return labelled.subset(labelled.marker >= 0)


def replace_arrays(obs: Observations, **arrays: np.ndarray) -> Observations:
    fields = {k: getattr(obs, k) for k in obs.__dataclass_fields__}
    fields.update(arrays)
    return Observations(**fields)


__all__ = ["Alternative", "AlternativesConfig", "handedness", "in_nominal_representative", "negated",
           "replace_arrays", "servo_alternatives", "with_markers", "without_blobs"]
