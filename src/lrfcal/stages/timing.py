"""Stage 3: the time of every beam and the motor angle at that time (the paper's linear interpolation).

Clocks: scan stamps are on the laser clock, joint-state stamps on the servo clock; for the same instant
``t_laser = t_servo + clock_offset_s``, so a beam time converts to servo time as ``t_laser - clock_offset_s``.

Array shapes: S scans, N beams per scan, J joint-state samples.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.errors import CalibrationError, InputError
from lrfcal.model.motor import JointGap, clock_offset_bound_s, dequantised, joint_gaps
from lrfcal.types import JointStates, Noted, Recording, Scans, joint_period_s, scan_spans

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


def beam_times(scans: Scans) -> FloatArray:
    """(S, N) laser-clock time of every beam: stamp + i * time_increment (each scan's own increment)."""
    return scans.beam_times_s


def unwrapped_positions(joints: JointStates) -> FloatArray:
    """(J,) joint positions with +-2 pi jumps removed (a wrapping encoder reading), for interpolation."""
    return np.unwrap(joints.positions_rad)


def motor_angles(
    times_s: ArrayLike,
    joints: JointStates,
    clock_offset_s: float = 0.0,
    tolerance_s: float | None = None,
) -> FloatArray:
    """Motor angle lambda at laser-clock times, by linear interpolation of the joint states.

    Args:
        times_s: any shape, laser clock.
        joints: J >= 2 samples sorted by stamp.
        clock_offset_s: t_servo = t_laser - clock_offset_s.
        tolerance_s: how far outside the joint-state span a time may fall (extrapolated linearly from the end
            segment); default one joint sample period.
    Returns:
        lambda_rad with the shape of ``times_s``. Wrapped encoder readings are unwrapped first, so angles can
        leave [-pi, pi) (the kinematics is 2 pi periodic).
    Raises:
        InputError: a time outside the joint-state span by more than ``tolerance_s``.
    """
    t = np.asarray(times_s, dtype=np.float64) - clock_offset_s
    ts = joints.stamps_s
    if ts.size < 2:
        raise InputError(f"joint states {joints.name}: {ts.size} sample(s); need at least 2 to interpolate")
    tol = joint_period_s(joints) if tolerance_s is None else float(tolerance_s)
    q = unwrapped_positions(joints)
    if t.size:
        lo, hi = float(np.min(t)), float(np.max(t))
        if lo < ts[0] - tol or hi > ts[-1] + tol:
            bad = lo if lo < ts[0] - tol else hi
            raise InputError(
                f"joint states {joints.name}: time {bad + clock_offset_s:.6f} s (laser clock, offset "
                f"{clock_offset_s:+.6f} s) outside the joint-state span [{ts[0]:.6f}, {ts[-1]:.6f}] s")
    lam = np.interp(t, ts, q)
    # linear extrapolation within the tolerance (np.interp holds the end values)
    before = t < ts[0]
    if np.any(before):
        slope = (q[1] - q[0]) / (ts[1] - ts[0])
        lam[before] = q[0] + slope * (t[before] - ts[0])
    after = t > ts[-1]
    if np.any(after):
        slope = (q[-1] - q[-2]) / (ts[-1] - ts[-2])
        lam[after] = q[-1] + slope * (t[after] - ts[-1])
    return lam


def beam_motor_angles(scans: Scans, joints: JointStates, clock_offset_s: float = 0.0) -> FloatArray:
    """(S, N) motor angle at every beam's own time (the motion during a scan accounted for)."""
    return motor_angles(beam_times(scans), joints, clock_offset_s)


def scan_angles(scans: Scans, joints: JointStates, clock_offset_s: float = 0.0) -> FloatArray:
    """(S,) one motor angle per scan, at its header.stamp (the paper's baseline: no motion within a scan)."""
    return motor_angles(scans.stamps_s, joints, clock_offset_s)


def covered_scans(scans: Scans, joints: JointStates, clock_offset_s: float = 0.0,
                  tolerance_s: float | None = None) -> BoolArray:
    """(S,) True for scans whose every beam time lies within the joint-state span (+- tolerance_s, default one
    joint sample period); use it to drop the ends of a recording before :func:`motor_angles`."""
    tol = joint_period_s(joints) if tolerance_s is None else float(tolerance_s)
    lo, hi = scan_spans(scans)
    lo, hi = lo - clock_offset_s, hi - clock_offset_s
    return (lo >= joints.stamps_s[0] - tol) & (hi <= joints.stamps_s[-1] + tol)


def subset_scans(scans: Scans, mask: np.ndarray) -> Scans:
    """The scans where ``mask`` (S,) is True (:meth:`lrfcal.types.Scans.subset`)."""
    return scans.subset(mask)


#: a scan whose motor angle the joint states interpolate worse than this share of the range noise (at its median
#: range) is left out; more than MAX_TRIMMED_SHARE of the scans so: refused
INTERPOLATION_SHARE = 0.5
MAX_TRIMMED_SHARE = 0.5


def interpolation_error_rad(joints: JointStates) -> FloatArray:
    """(J - 1,) a bound on how far the linear interpolation of the joint states can be from the motor's angle within
    each interval between samples: half the change of the slope at its two ends times its length, beyond what two
    encoder steps make of the slopes.

    A change of the motor's speed by dv within an interval of length h leaves the interpolation up to dv h / 4 off, and
    changes the slope at one of its ends by at least dv / 2; a steady motion (a sweep's cruise, a standstill) leaves
    none. The slopes are divided differences, so an interval much longer than the others (a gap in the stream) is
    bounded by its own length. Encoder quantisation (the smallest step the joint states report) is not counted: the
    per-scan widening of the covariance carries it."""
    q = unwrapped_positions(joints)
    J = q.size
    out = np.zeros(max(J - 1, 0))
    if J < 3:
        return out
    h = np.maximum(np.diff(joints.stamps_s), 1e-12)
    steps = np.abs(np.diff(q))
    quantum = float(steps[steps > 0].min()) if np.any(steps > 0) else 0.0
    slope = np.diff(q) / h
    # at samples 1 .. J - 2: the change of slope, less what the encoder's step makes of the two slopes
    turn = np.maximum(np.abs(np.diff(slope)) - quantum / h[:-1] - quantum / h[1:], 0.0)
    out[:-1] = turn * h[:-1] / 2.0  # interval j ends at sample j + 1
    out[1:] = np.maximum(out[1:], turn * h[1:] / 2.0)  # ... and starts at sample j
    return out


def _poorly_interpolated(scans: Scans, joints: JointStates, tau0: float, range_sigma_m: float
                         ) -> tuple[NDArray[np.bool_], float]:
    """(S,) the scans whose motor angle the joint states interpolate worse than INTERPOLATION_SHARE of the range
    noise at their median range (none for a step-and-scan rig, whose angle is its scan's own), and the worst bound
    [rad]."""
    S = scans.stamps_s.size
    if scans.angle_per_scan or joints.stamps_s.size < 3:
        return np.zeros(S, dtype=bool), 0.0
    err = interpolation_error_rad(joints)
    t0, t1 = scan_spans(scans)
    last = err.size - 1
    i0 = np.clip(np.searchsorted(joints.stamps_s, t0 - tau0) - 1, 0, last)
    i1 = np.clip(np.searchsorted(joints.stamps_s, t1 - tau0) - 1, 0, last)
    bound = np.maximum(err[i0], err[i1])
    bad = np.zeros(S, dtype=bool)
    near = np.flatnonzero(bound > 0)  # only scans next to a speed change can be misplaced: their ranges are read
    if near.size:
        r = np.where(np.isfinite(scans.ranges_m[near]), scans.ranges_m[near], np.nan)
        some = np.isfinite(r).any(axis=1)  # a scan without returns has nothing to misplace
        reach = np.zeros(near.size)
        reach[some] = np.nanmedian(r[some], axis=1)
        bad[near] = bound[near] * reach > INTERPOLATION_SHARE * range_sigma_m
    return bad, float(bound.max(initial=0.0))


def usable_scans(recording: Recording, tau0: float, range_sigma_m: float | None = None
                 ) -> Noted[tuple[Scans, JointStates]]:
    """The joint states without encoder spikes and the scans they cover at clock offset ``tau0``, outside the gaps of
    the joint states that may hide a reversal or a stop (:func:`_outside_gaps`); with the range
    noise ``range_sigma_m``, also without the scans whose motor angle the joint states do not interpolate well
    enough (a speed change between sparse samples, :func:`interpolation_error_rad`). The joint states returned have
    most of the encoder's quantisation taken out (:func:`without_quantisation`); the notes say what was dropped.

    Raises:
        CalibrationError: no scan lies within the joint states' time span, most scans fall in gaps of the joint
            states that may hide the servo's motion, or most fall between joint states too sparse to interpolate
            their motor angle.
    """
    notes: list[str] = [] if recording.report is None else list(recording.report.left_out)  # a cut bag, a clock step
    joints, n_spikes = remove_spikes(recording.joints)  # joint states: spikes out, uncovered scans trimmed
    if n_spikes:
        notes.append(f"{n_spikes} joint-state samples that jump away from their neighbours dropped")
    covered = covered_scans(recording.scans, joints, tau0)
    if not covered.any():
        raise CalibrationError(
            f"no scan lies within the joint states' time span at clock offset {tau0:+.3f} s (laser "
            f"{recording.scans.stamps_s[0]:.3f}-{recording.scans.stamps_s[-1]:.3f} s, servo {joints.stamps_s[0]:.3f}-"
            f"{joints.stamps_s[-1]:.3f} s): pass the offset with --clock-offset"
        )
    scans = subset_scans(recording.scans, covered)
    if not covered.all():
        notes.append(f"{int((~covered).sum())} of {covered.size} scans outside the joint states' time span trimmed")
    outside = _outside_gaps(scans, joints, tau0)
    scans = outside.value
    notes += outside.notes
    if range_sigma_m is None:
        return Noted((scans, without_quantisation(joints, scans)), tuple(notes))
    poor, worst = _poorly_interpolated(scans, joints, tau0, range_sigma_m)
    if poor.any():
        why = (f"the joint states (every {joint_period_s(joints) * 1000:.0f} ms) interpolate their motor angle only to "
               f"{worst * 1000:.2g} mrad where the servo changes speed between samples")
        if poor.mean() > MAX_TRIMMED_SHARE:
            raise CalibrationError(f"{int(poor.sum())} of {poor.size} scans: {why}; record the joint states faster "
                                   "(at least the scan rate)")
        notes.append(f"{int(poor.sum())} of {poor.size} scans left out: {why}")
        scans = subset_scans(scans, ~poor)
    return Noted((scans, without_quantisation(joints, scans)), tuple(notes))


def scans_in_gaps(scans: Scans, gaps: tuple[JointGap, ...], clock_offset_s: float = 0.0) -> BoolArray:
    """(S,) True for scans with a beam inside one of the joint states' ``gaps`` (servo clock) at the clock offset."""
    lo, hi = scan_spans(scans)
    lo, hi = lo - clock_offset_s, hi - clock_offset_s
    inside = np.zeros(lo.size, dtype=bool)
    for g in gaps:
        inside |= (hi > g.start_s) & (lo < g.end_s)
    return inside


def _outside_gaps(scans: Scans, joints: JointStates, tau0: float) -> Noted[Scans]:
    """The scans outside the gaps of the joint states that may hide the servo's motion (lrfcal.model.motor.joint_gaps;
    a step-and-scan rig's angle is its scan's own: kept), with a note naming the longest; the gaps bridged where the
    motion was steady are named in a note too.

    Raises:
        CalibrationError: more than MAX_TRIMMED_SHARE of the scans fall in such gaps.
    """
    if scans.angle_per_scan:
        return Noted(scans)
    notes: list[str] = []
    gaps = joint_gaps(joints.stamps_s, joints.positions_rad)
    hiding = tuple(g for g in gaps if g.hides)
    steady = [g for g in gaps if not g.hides]
    if steady:
        longest = max(steady, key=lambda g: g.length_s)
        notes.append(f"the motor angle interpolated across {len(steady)} gap(s) of the joint states where the servo's "
                     f"motion was steady; the longest: {longest.describe(float(joints.stamps_s[0]))}")
    if not hiding:
        return Noted(scans, tuple(notes))
    inside = scans_in_gaps(scans, hiding, tau0)
    longest = max(hiding, key=lambda g: g.length_s)
    why = (f"{len(hiding)} gap(s) of the joint states may hide the servo's motion, across which the motor angle cannot "
           f"be interpolated; the longest: {longest.describe(float(joints.stamps_s[0]))}")
    if inside.mean() > MAX_TRIMMED_SHARE:
        raise CalibrationError(f"{int(inside.sum())} of {inside.size} scans fall where {why}; record the joint states "
                               "without gaps (at least the scan rate throughout)")
    if inside.any():
        notes.append(f"{int(inside.sum())} of {inside.size} scans left out: {why}")
    return Noted(subset_scans(scans, ~inside), tuple(notes))


def without_quantisation(joints: JointStates, scans: Scans) -> JointStates:
    """The joint states with most of the encoder's quantisation taken out where the motion is smooth
    (lrfcal.model.motor.dequantised); as they are for a step-and-scan rig (Scans.angle_per_scan: its angle is read
    at a standstill, not interpolated along a motion)."""
    if scans.angle_per_scan:
        return joints
    return JointStates(stamps_s=joints.stamps_s, positions_rad=dequantised(joints.stamps_s, joints.positions_rad),
                       name=joints.name)


__all__ = ["beam_motor_angles", "beam_times", "clock_offset_bound", "covered_scans", "interpolation_error_rad",
           "joint_period_s", "motor_angles", "remove_spikes", "scan_angles", "scan_spans", "scans_in_gaps",
           "subset_scans", "sweep_passes", "unwrapped_positions", "usable_scans", "without_quantisation"]


def sweep_passes(scan_lambda_rad: ArrayLike, min_fraction: float = 0.1, min_scans: int = 5) -> NDArray[np.int64]:
    """(S,) pass index of every scan: 0, 1, 2, ... for each monotonic run of the sweep (a reversal of the motor's
    direction starts a new pass).

    Standstills carry the previous direction; runs that move less than ``min_fraction`` of the whole sweep's range
    or last fewer than ``min_scans`` scans (encoder jitter, a spike in the joint states) are merged into the run
    before them.
    """
    lam = np.asarray(scan_lambda_rad, dtype=float)
    S = lam.size
    if S < 2:
        return np.zeros(S, dtype=np.int64)
    span = float(np.ptp(lam))
    d = np.sign(np.diff(lam))
    d[np.abs(np.diff(lam)) < 1e-9] = 0.0
    nz = np.flatnonzero(d)
    if nz.size == 0:
        return np.zeros(S, dtype=np.int64)
    d[: nz[0]] = d[nz[0]]
    for i in range(1, d.size):
        if d[i] == 0:
            d[i] = d[i - 1]
    # runs of equal direction [start, end) over the S - 1 steps; a short run takes the previous run's direction
    for _ in range(S):
        starts = np.concatenate([[0], np.flatnonzero(np.diff(d) != 0) + 1])
        ends = np.concatenate([starts[1:], [d.size]])
        short = [k for k in range(1, starts.size)
                 if ends[k] - starts[k] < min_scans or abs(lam[ends[k]] - lam[starts[k]]) < min_fraction * span]
        if not short:
            break
        k = short[0]
        d[starts[k]:ends[k]] = d[starts[k] - 1]
    runs = [[int(s0), int(e0)] for s0, e0 in zip(starts, ends, strict=True)]
    out = np.zeros(S, dtype=np.int64)
    for k, (s0, _) in enumerate(runs):
        out[s0 + 1:] = k
    return out


def clock_offset_bound(joints: JointStates) -> tuple[float, float]:
    """The largest clock offset [s] a calibration with these joint states may start from or report
    (lrfcal.model.motor.clock_offset_bound_s, from the durations of the sweep's passes, whatever the offset), and the
    shortest pass's duration [s]. The passes are found on at most PASS_SAMPLES of the samples, evenly spread."""
    t = joints.stamps_s
    if t.size < 2:
        return clock_offset_bound_s([]), math.inf
    pick = np.unique(np.linspace(0, t.size - 1, min(t.size, PASS_SAMPLES)).astype(np.int64))
    t = t[pick]
    passes = sweep_passes(unwrapped_positions(joints)[pick])
    durations = [float(np.ptp(t[passes == k])) for k in range(int(passes.max()) + 1)]
    return clock_offset_bound_s(durations), min(durations)


#: joint-state samples at most that the sweep's passes are found on (lrfcal.stages.timing.clock_offset_bound)
PASS_SAMPLES = 5000


def remove_spikes(joints: JointStates, threshold_rad: float = 0.05, window: int = 5) -> tuple[JointStates, int]:
    """Drop joint-state samples that jump away from their neighbours (a Hampel filter: more than ``threshold_rad``
    from the median of the ``window`` samples on each side). Returns the cleaned joint states and the count."""
    q = unwrapped_positions(joints)
    n = q.size
    if n < 2 * window + 1:
        return joints, 0
    pad = np.pad(q, window, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(pad, 2 * window + 1)
    med = np.median(windows, axis=1)
    bad = np.abs(q - med) > threshold_rad
    if not bad.any():
        return joints, 0
    return JointStates(stamps_s=joints.stamps_s[~bad], positions_rad=joints.positions_rad[~bad],
                       name=joints.name), int(bad.sum())
