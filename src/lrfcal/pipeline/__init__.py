"""The calibration, as one method: the beams' times, the observation sets and their starts, the estimates, the
checks, the reprojection.

    calibrate(recording)
      1. the scans the joint states cover, each beam's time              lrfcal.stages.timing
      2. one of two ways through the same loop (lrfcal.pipeline.loop): observe, estimate from each candidate
         start, choose, choose the sets again until they stand, widen by the systematics, check
         with markers (the seed paper, Sec. III and IV-C)               lrfcal.stages.markers.MarkerWay
         from the scene's planes alone (targetless)                      lrfcal.stages.scene.PlaneWay
         both use one model (lrfcal.model) and one engine (lrfcal.estimate.engine), which the loop calls
      3. refused when a check fails                                      lrfcal.estimate.checks
      4. every beam reprojected before and after; tunnel planes          lrfcal.stages.reproject, lrfcal.stages.geometry

The DH search a targetless calibration's starts need runs ahead, in forked children (lrfcal.pipeline.search); what
the calibration tells its caller meanwhile goes through one observer (lrfcal.result.Observer).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import replace
from typing import Protocol, TypedDict, TypeVar

import numpy as np

from lrfcal.config import DEFAULT_NOMINAL_TOLERANCE, DEFAULT_RANGE_SIGMA_M, CalibConfig, Stopwatch
from lrfcal.errors import CalibrationError, ClockOffsetError, ClockStartError, InputError
from lrfcal.estimate.checks import clock_offset_check, refuse_failed
from lrfcal.model.kinematics import refuse_placeholder_dh
from lrfcal.model.motor import CLOCK_OFFSET_PASS_SHARE, MAX_CLOCK_OFFSET_S
from lrfcal.pipeline.loop import Way, estimated
from lrfcal.pipeline.search import proposal_ahead
from lrfcal.result import CalibrationResult, Observer
from lrfcal.runtime.forked import on_cores
from lrfcal.stages import geometry, reproject, timing
from lrfcal.stages.clocksearch import MAX_START_ERROR_RAD, line_up
from lrfcal.stages.markers import STAGES, MarkerWay
from lrfcal.stages.scene import PlaneWay
from lrfcal.stages.timing import usable_scans
from lrfcal.types import FloatArray, JointStates, Noted, Recording, Scans, Solution, TunnelGeometry


def calibrate(recording: Recording, config: CalibConfig | None = None, observer: Observer | None = None
              ) -> CalibrationResult:
    """Run stages 1-8 on a recording; see the module docstring.

    ``observer`` (lrfcal.result.Observer) is told each stage as it starts (for a CLI's status line), the marker way's
    blobs matched to the marker map once its alternative is chosen (for the intensity figure, drawn while the
    refinement goes on), and the result once its checks passed, before its clouds are made (step 4: e.g. to draw
    figures that need no clouds meanwhile).
    Raises CalibrationError (exit code 3) with the reason when the data do not support a trustworthy result,
    unless ``config.force``, which records the failed checks in the result instead.
    """
    config = config or CalibConfig()
    if config.range_sigma_m is None:  # the sensor's noise as the rig file declares it, else the UTM-30LX-EW's
        declared = recording.nominal.range_sigma_m
        config = config.replace(range_sigma_m=DEFAULT_RANGE_SIGMA_M if declared is None else declared)
    if config.dh_tolerance is None:  # the nominal's 1-sigma as the rig file declares it, else the default
        config = config.replace(dh_tolerance=recording.nominal.dh_tolerance or DEFAULT_NOMINAL_TOLERANCE)
    if config.range_pattern or recording.nominal.range_pattern:  # the rig file's declaration or the command line's:
        # both say so, and the rig written with the result (`lrfcal check` reads a new recording with it)
        config = config.replace(range_pattern=True)
        recording = replace(recording, nominal=replace(recording.nominal, range_pattern=True))
    try:
        return _calibrate(recording, config, observer or Observer())
    except ClockOffsetError as err:  # the refusal names the clock offset: only what the reader left out is added
        if not (left := _left_out_hint(recording)):
            raise
        raise type(err)(f"{err}; {left}") from None
    except CalibrationError as err:
        hint = "; ".join(h for h in (_trimmed_hint(recording, config.clock_offset_s) or _start_hint(
            config.clock_offset_s), _left_out_hint(recording)) if h)
        if not hint:
            raise
        raise CalibrationError(f"{err}; {hint}") from None


def _left_out_hint(recording: Recording) -> str:
    """What the reader left out of the recording (a clock step's other side, a cut bag's lost end; ReadReport's
    left_out), for a refusal: the data refused are not the whole recording (empty when nothing was left out)."""
    if recording.report is None or not recording.report.left_out:
        return ""
    return "note: the calibration had only part of the recording: " + "; ".join(recording.report.left_out)


def _start_hint(tau0: float) -> str:
    """A hint for a refusal of a calibration started from a clock offset ``tau0`` other than 0 (empty at 0)."""
    if tau0 == 0.0:
        return ""
    return (f"note: the calibration started from --clock-offset {tau0:+g} s; a start whose motor angle is off by more "
            "than a few degrees (the sweep's speed times the start's error) does not find the true offset, and the fit "
            "from there can blame the markers; if the offset is not known, leave --clock-offset at 0 for the "
            "calibration to estimate it")


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


def _calibrate(recording: Recording, config: CalibConfig, observer: Observer) -> CalibrationResult:
    """:func:`calibrate` with ``config.range_sigma_m`` resolved: the method, the same steps for both ways."""
    if _targetless(recording, config):  # the one place the way is chosen
        return _through(PlaneWay, recording, config, observer, compare=False)
    return _through(MarkerWay, recording, config, observer, compare=config.compare_targetless)


Ob = TypeVar("Ob")
St = TypeVar("St")
S = TypeVar("S")


class WayOf(Protocol[Ob, St, S]):
    """A way's class: its stages (as the observer is told them), the notes every result of it begins with, whether
    its starts need the DH search's proposal, and the way on a recording (lrfcal.pipeline.loop.Way)."""

    STAGES: tuple[str, ...]
    NOTES: tuple[str, ...]
    SEARCH: bool

    def __call__(self, recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch,
                 observer: Observer) -> Way[Ob, St, S]: ...


def _through(way_of: WayOf[Ob, St, S], recording: Recording, config: CalibConfig, observer: Observer, compare: bool
             ) -> CalibrationResult:
    """The four steps through one way (``compare``: the targetless calibration of the same recording beside it)."""
    clock = Stopwatch(observer.stage, way_of.STAGES)
    timed = usable_scans(recording, config.clock_offset_s, config.range_sigma_m)  # 1.
    scans, joints = timed.value
    bound = _clock_start(scans, joints, config.clock_offset_s)
    covered = replace(recording, scans=scans)
    way = way_of(covered, joints, config, clock, observer)
    # the DH search the way's starts need, begun now in forked children (lrfcal.pipeline.search)
    with proposal_ahead(scans, joints) if way_of.SEARCH else contextlib.nullcontext() as proposal:
        fit = estimated(way, proposal)  # 2. (lrfcal.pipeline.loop)
    fit = replace(fit, checks=(clock_offset_check(fit.solution, *bound), *fit.checks))  # what both ways check
    refuse_failed(list(fit.checks), config)  # 3.
    joints = joints.signed(fit.servo_sign)
    opinion = _targetless_opinion(recording, config) if compare else Noted({})  # without its markers, for the report
    observer.fitted(fit)
    clouds = _reproject(covered, joints, fit.solution, config, clock)  # 4.
    return replace(fit, **clouds, timings_s=clock.laps, notes=(*way_of.NOTES, *timed.notes, *fit.notes, *opinion.notes),
                   side_by_side={**fit.side_by_side, **opinion.value}, config=config)


CLOCK_START = "clock offset: --clock-offset"


def _clock_start(scans: Scans, joints: JointStates, tau0: float) -> tuple[float, float]:
    """The bound on the clock offset of this recording and its shortest pass [s]
    (lrfcal.stages.timing.clock_offset_bound).

    Raises:
        ClockStartError: the start ``tau0`` (``--clock-offset``) lies beyond it, or (a start other than 0) too far
            from where the sweep's two directions line up (lrfcal.stages.clocksearch): the solve would settle near it.
    """
    bound, shortest = timing.clock_offset_bound(joints)
    if abs(tau0) > bound:
        raise ClockStartError(
            f"{CLOCK_START} {tau0:+g} s is beyond the +-{bound * 1000:.0f} ms a calibration of this recording starts "
            f"from (the smaller of {MAX_CLOCK_OFFSET_S:g} s, beyond which the laser's and the servo's clocks differ "
            "rather than lag and the bag reader applies the offset from the receive times, and "
            f"1/{1 / CLOCK_OFFSET_PASS_SHARE:.0f} of the sweep's shortest pass, {shortest:.3g} s: the motor angles "
            "of its two directions then lie too far apart for the solve to find the offset): the solve would settle "
            "on a wrong offset near the start; give the latency between the laser's and the servo's stamps, or leave "
            "--clock-offset at 0 for the calibration to estimate it")
    found = line_up(scans, joints, bound, tau0) if tau0 != 0.0 else None
    if found is not None and found.refutes(tau0):
        ms, deg = 1000.0, math.degrees(found.start_error_rad(tau0))
        raise ClockStartError(
            f"{CLOCK_START} {tau0:+g} s: the sweep's two directions see the same scene at {found.offset_s * ms:+.0f} "
            f"ms (searched over +-{bound * ms:.0f} ms; their ranges differ by {found.mismatch_m * ms:.1f} mm there, "
            f"{found.start_mismatch_m * ms:.1f} mm at the start), {deg:.1f} deg of motor angle from the start, "
            f"farther than the solve finds the offset from ({math.degrees(MAX_START_ERROR_RAD):g} deg); start from "
            f"--clock-offset {found.offset_s:+.3g}" + (" (or leave it at 0)" if found.offset_s != 0.0 else ""))
    return bound, shortest


def _targetless(recording: Recording, config: CalibConfig) -> bool:
    """Whether to calibrate from the scene's planes: when asked, or by default when there are no tape distances.

    Raises:
        InputError: markers asked for without tape distances, or a clock offset that is not a number.
    """
    if not math.isfinite(config.clock_offset_s):
        raise InputError(f"clock offset: expected a finite number of seconds, got {config.clock_offset_s!r}")
    refuse_placeholder_dh(recording.nominal.dh, "nominal.yaml", "calibrating")
    targetless = config.targetless or (config.targetless is None and recording.tape is None)
    if not targetless and recording.tape is None:
        raise InputError("calibration with markers needs the tape distances (distances.csv); without markers, "
                         "calibrate targetless (--targetless)")
    return bool(targetless)


def _targetless_opinion(recording: Recording, config: CalibConfig) -> Noted[dict[str, Solution]]:
    """The targetless calibration of a recording with markers, beside the marker results (empty, with a note, when it
    is refused)."""
    try:
        tl = calibrate(recording, config.replace(targetless=True, force=False, geometry=False, clouds=False))
        return Noted({"targetless (markers ignored)": tl.solution})
    except CalibrationError as err:
        return Noted({}, (f"the targetless calibration of the same recording was refused: {err}",))


class _Clouds(TypedDict, total=False):
    """4.'s fields of the result (CalibrationResult's names): the clouds in M, their intensities, the geometry."""

    cloud_before_M: FloatArray
    cloud_after_M: FloatArray
    cloud_intensity: FloatArray
    geometry_before: TunnelGeometry | None
    geometry_after: TunnelGeometry | None


def _reproject(recording: Recording, joints: JointStates, sol: Solution, config: CalibConfig, clock: Stopwatch
               ) -> _Clouds:
    """4.: every ``config.cloud_stride``-th scan reprojected in M with the nominal and with the calibrated DH (and
    the range offset), and the tunnel's planes and dimensions in each; the result's fields."""
    empty = np.zeros((0, 3))
    if not config.clouds:
        return {"cloud_before_M": empty, "cloud_after_M": empty, "cloud_intensity": np.zeros(0)}
    scans = recording.scans
    lambda_beams = timing.motor_angles(scans.beam_times_s, joints, clock_offset_s=sol.clock_offset_s,
                                       tolerance_s=math.inf)
    (before, after), intensity = reproject.reproject_clouds(scans, lambda_beams, (recording.nominal.dh, sol.params.dh),
                                                            config.cloud_stride,
                                                            ({}, sol.intrinsic_values))
    clock.lap("reprojection")
    out: _Clouds = {"cloud_before_M": before, "cloud_after_M": after, "cloud_intensity": intensity}
    if config.geometry:
        out["geometry_before"], out["geometry_after"] = on_cores(geometry.tunnel_geometry, [(before,), (after,)])
        clock.lap("geometry")
    return out


__all__ = ["STAGES", "CalibConfig", "Observer", "Way", "calibrate"]
