"""The marker way's candidate starts and the one chosen (lrfcal.stages.markers.MarkerWay's ``sets_at``, ``reselect``
before the choice, ``choose``; stages 4-6).

The discrete alternatives a marker-only solve can start from: each direction of the servo (the data cannot tell them
apart), its blobs matched to the marker map (lrfcal.stages.matching, from the nominal DH or the DH search's
candidates), its start (mount pose from that alignment, DH from the nominal) and the observability judged there; its
marker-only solve, chosen again while the data contradict a scale held at 1 and while blobs disagree with the map.
The declared direction is kept where its estimate is near the nominal, else the other is tried too and the direction
chosen (lrfcal.estimate.checks.servo_direction); then the map's other handedness where the nominal DH prefer it, and
the DH representative nearer the nominal, each a further start.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate import observability
from lrfcal.estimate.checks import CheckConfig, far_from_nominal, mirror_check, nearer_mirror, servo_direction
from lrfcal.estimate.information import information_at
from lrfcal.model.kinematics import DH, Params, Pose, dh_twins, homogeneous
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.motor import Clock, MotorClock
from lrfcal.stages import association, joint, matching, start
from lrfcal.stages.marker_sets import Alternative, FromStart, MarkerSets, Once, Stood
from lrfcal.types import Association, Detections, Fit, JointStates, MarkerMap, Nominal, Observations, Tried

FloatArray = NDArray[np.float64]


class AlternativesConfig(CheckConfig, matching.MatchConfig, Protocol):
    """The configuration the start reads: its slice of lrfcal.config.CalibConfig (which satisfies it): the checks'
    (the nominal tolerance, the chi-square limit, the range noise), the matching's and the clock's start."""

    @property
    def clock_offset_s(self) -> float: ...


class _NoMatch(CalibrationError):
    """The blobs could not be matched to the markers (for one direction of the servo): the other is tried."""


@dataclass(frozen=True)
class Direction:
    """A start: the servo turning ``sign``-wards (``every_attitude``: the association's DH search tries every
    attitude, as for the first direction tried)."""

    sign: int
    every_attitude: bool = True


@dataclass(frozen=True)
class Mirrored:
    """A start: the chosen fit ``of`` in the marker map's other handedness, from its nearest mirror twin
    (lrfcal.estimate.checks.nearer_mirror's ``twin``: name, DH, isometry, the two distances from the nominal)."""

    of: Fit[MarkerSets]
    twin: tuple[str, DH, FloatArray, float, float]


@dataclass(frozen=True)
class Turned:
    """A start: the chosen fit ``of`` from its turned twin, the DH representative nearer the nominal."""

    of: Fit[MarkerSets]


#: the marker way's candidate starts
Start = Direction | Mirrored | Turned


@dataclass(frozen=True)
class Matching:
    """What the directions' starts are matched from: the marker returns by the servo's sign (their motor angles
    signed), the blobs, the marker map, the associations made from the nominal DH so far (by sign) and whether the DH
    search runs (neither direction associates well from the nominal DH)."""

    returns: Mapping[int, Observations]
    detections: Detections
    markers: MarkerMap
    from_nominal: Mapping[int, Association | None]
    search: bool


def matching_of(returns: Observations, detections: Detections, markers: MarkerMap, nominal: Nominal,
                config: AlternativesConfig) -> Matching:
    """4.: the returns by direction, and whether the DH search runs: only when neither direction associates well from
    the nominal values (the other is associated only if the declared does not)."""
    signed = {1: returns, -1: replace_arrays(returns, lambda_rad=-returns.lambda_rad)}
    first = {1: matching.associate_nominal(signed[1], detections, markers, nominal, config)}
    if not (first[1] is not None and matching.good(first[1], signed[1], config)):
        first[-1] = matching.associate_nominal(signed[-1], detections, markers, nominal, config)
    search = not any((a := first.get(s)) is not None and matching.good(a, signed[s], config) for s in (1, -1))
    return Matching(signed, detections, markers, first, search)


def direction_sets(m: Matching, at: Direction, joints: JointStates | None, nominal: Nominal,
                   config: AlternativesConfig, sensor: MarkerSensor) -> MarkerSets:
    """5.: the marker-only sets of one direction of the servo: the blobs matched to the map (from the nominal DH, or
    the DH search's candidates), the start (mount pose from that alignment, DH from the nominal or the candidate),
    the observability judged there; ``joints``: the joint states the clock offset is estimated by (None: held).

    Raises CalibrationError when the blobs could not be matched (:class:`_NoMatch`), or when the data do not determine
    the DH parameters (judged at the start, before any solver runs).
    """
    sign, returns = at.sign, m.returns[at.sign]
    first = (m.from_nominal[sign] if sign in m.from_nominal
             else matching.associate_nominal(returns, m.detections, m.markers, nominal, config))
    start_dh, assoc = (matching.associate_search(returns, m.detections, m.markers, nominal, config, first,
                                                 every_attitude=at.every_attitude)
                       if m.search else (nominal.dh, first))
    if assoc is None:
        raise _NoMatch("association: no alignment of the blobs with the marker map (check the tape distances' file "
                       "and unit, and the marker radius)")
    markers = association.unmirror(m.markers) if assoc.mirrored else m.markers
    matched = with_markers(returns, assoc.blob_to_marker)
    n_matched = len(np.unique(matched.marker))
    if n_matched < 4:
        raise _NoMatch(f"only {n_matched} markers matched to detections (need >= 4); alignment RMS "
                       f"{assoc.rms_m * 1000:.1f} mm")
    params = Params(Pose.from_matrix(assoc.T_W_M), start_dh)
    motor = None if joints is None else MotorClock.from_joints(joints.signed(sign))
    info, names = information_at(matched, markers.positions_W, params, sensor=sensor,
                                 clock=Clock(motor, config.clock_offset_s), sides=False)
    obs = observability.analyse(info, names, params.dh.alpha)
    if not obs.determined:
        raise CalibrationError(
            f"the recording does not determine {', '.join(obs.undetermined) or 'the DH parameters'} "
            f"({obs.describe()}: 1-sigma {obs.weakest_sigma_in_limits:.3g} times the limit, judged at the start): "
            f"{obs.hint()}")
    return MarkerSets(Alternative(sign, markers, assoc, matched, params, motor), params, config.clock_offset_s,
                      FromStart())


def mirrored_sets(at: Mirrored) -> MarkerSets:
    """The sets of the chosen fit in the marker map's other handedness, from its mirror twin: the map mirrored, the
    mount F T_W_M Q (F the map's reflection, Q the twin's isometry in M), with a note.

    Tape distances fix the map only up to a reflection. With the map mirrored, the estimate's mirror twin explains the
    data exactly as well. Near a scan plane perpendicular to the motor axis the association cannot tell the
    handedness, so it is chosen by the nominal DH (:func:`chosen`: the result must then pass the mirror check)."""
    name, twin, Q, d_est, d_twin = at.twin
    sol, alt = at.of.solution, at.of.sets.alt
    T = np.diag([1.0, 1.0, -1.0, 1.0]) @ sol.params.mount.matrix() @ homogeneous(Q, np.zeros(3))
    note = (f"the marker map matched in the other handedness: its mirror image ({name}) is {d_twin:.1f} nominal "
            f"tolerances from the nominal DH, the first estimate {d_est:.1f}; solved again in the map's mirror image")
    mirrored = replace(alt, markers=association.unmirror(alt.markers), notes=(*alt.notes, note),
                       assoc=replace(alt.assoc, mirrored=not alt.assoc.mirrored, T_W_M=T))
    return MarkerSets(mirrored, Params(Pose.from_matrix(T), twin), sol.clock_offset_s, Once())


def turned_sets(at: Turned) -> MarkerSets:
    """The sets of the chosen fit from its turned twin (-a, -alpha, b, beta + pi with the mount turned by pi about the
    motor axis: the same rig, lrfcal.model.kinematics.dh_twins): a solve from the mirror image or from a coarse start
    can end in the other representative, right as a rig but with a, alpha and beta far from the rig file's."""
    sol = at.of.solution
    _, twin, Q = dh_twins(sol.params.dh)[0]
    turned = Params(Pose.from_matrix(sol.params.mount.matrix() @ homogeneous(Q, np.zeros(3))), twin)
    return MarkerSets(at.of.sets.alt, turned, sol.clock_offset_s, Once())


def reselected(fit: Fit[MarkerSets], config: AlternativesConfig) -> MarkerSets | Fit[MarkerSets] | None:
    """A direction's sets chosen again at its marker-only solution: a scale held at 1 that the data contradict freed
    (before any marker is judged moved: a range scale moves every far marker from its tape position; the scales'
    score tests read this solution), then the blobs whose returns the fit rejects (matched wrongly, or on a marker
    that is not where the tape puts it) left out, at most three times; where the fit does not determine the DH
    parameters, its residuals cannot tell them, and the disagreement is left for the joint solution to judge (the
    sets stand, with it). None: they stand."""
    sets, sol = fit.sets, fit.solution
    alt, step = sets.alt, sets.step
    if not isinstance(step, FromStart):
        return None  # a further start is solved once
    left_out = step.left_out
    if left_out < 0:
        if off := joint.most_off(sol, config.max_reduced_chi2):
            alt = replace(alt, notes=(*alt.notes, *off.notes), estimate=(*alt.estimate, off.value))
            return MarkerSets(alt, sol.params, sol.clock_offset_s, FromStart())
        left_out = 0
    if left_out >= 3:
        return None
    assert config.range_sigma_m is not None  # resolved by lrfcal.pipeline.calibrate
    bad, why = association.inconsistent_blobs(alt.matched, sol, alt.markers, config.range_sigma_m)
    if not bad.size:
        return None
    if not observability.within_limits(sol.dh_sigma):  # its residuals cannot tell: the joint solution will
        return Fit(replace(sets, alt=replace(alt, unjudged=why.removesuffix(": left out")), step=Stood()), sol)
    assoc, matched = without_blobs(alt.assoc, alt.matched, bad, why)
    alt = replace(alt, assoc=assoc, matched=matched, notes=(*alt.notes, why))
    return MarkerSets(alt, sol.params, sol.clock_offset_s, FromStart(left_out + 1))


def chosen(tried: Sequence[Tried[Start, MarkerSets]], nominal: DH, config: AlternativesConfig
           ) -> Fit[MarkerSets] | list[Start]:
    """6.: the alternative chosen from the starts ``tried`` so far, or the further starts it needs: the declared
    direction of the servo unless its estimate is far from the nominal (then the other direction too, and the one
    the nominal DH fit: lrfcal.estimate.checks.servo_direction), then the map's other handedness where the nominal DH
    prefer its mirror twin (kept when it passes the mirror check), then the DH representative nearer the nominal.

    Raises:
        CalibrationError: the declared direction failed for another reason than its match (e.g. the layout does not
            determine the DH: the other direction does not help), no direction matched, or the nominal DH contradict
            the declared direction.
    """
    directions = [t for t in tried if isinstance(t.start, Direction)]
    for t in tried:  # a singular system ends the calibration wherever it arises
        if isinstance(t.outcome, np.linalg.LinAlgError):
            raise t.outcome
    declared = directions[0]
    if isinstance(declared.outcome, CalibrationError) and not isinstance(declared.outcome, _NoMatch):
        raise declared.outcome
    if len(directions) == 1 and (declared.fit is None or far_from_nominal(declared.fit.solution.params.dh, nominal,
                                                                          config)):
        return [Direction(-1, every_attitude=declared.fit is None)]
    fits = {t.fit.sets.alt.sign: t.fit for t in directions if t.fit is not None}
    if not fits:
        assert isinstance(declared.outcome, CalibrationError)
        raise declared.outcome
    best = fits[servo_direction({sign: f.solution for sign, f in fits.items()}, nominal, config)]
    mirrored = next((t for t in tried if isinstance(t.start, Mirrored)), None)
    if mirrored is None:
        twin = nearer_mirror(best.solution.params.dh, nominal, config, best.solution.dh_sigma)
        if twin is not None:
            return [Mirrored(best, twin)]
    elif (m := mirrored.fit) is not None and mirror_check(m.solution.params.dh, nominal, config,
                                                          m.solution.dh_sigma).passed:
        best = m  # otherwise the first solution stays (and the mirror check refuses it)
    turned = next((t for t in tried if isinstance(t.start, Turned)), None)
    if turned is None:
        if start.turned_is_nearer(best.solution.params.dh, nominal):
            return [Turned(best)]
    elif turned.fit is not None:
        best = turned.fit
    return best


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


__all__ = ["AlternativesConfig", "Direction", "Matching", "Mirrored", "Start", "Turned", "chosen", "direction_sets",
           "matching_of", "mirrored_sets", "reselected", "replace_arrays", "turned_sets", "with_markers",
           "without_blobs"]
