"""A read recording: the scans, the joint states, the tape distances, the nominal values, and what the reader
kept, skipped, masked and assumed. Array shapes: S scans, N beams per scan, J joint-state samples, P measured pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.kinematics import DH, Pose
from lrfcal.types.arrays import FloatArray, IntArray
from lrfcal.types.sources import LogLayout, ScanSource, ServoSource

#: Scans' beam_counts when none are given: every scan carried all N beams (:meth:`Scans.__post_init__` fills them in)
_EVERY_BEAM: IntArray = np.zeros(0, dtype=np.int64)

@dataclass(frozen=True)
class Scans:
    """All LaserScan messages of a recording, in time order (scans the reader skipped are not here).

    stamps_s (S,): time of beam 0 (laser clock); ranges_m (S, N): NaN where the driver reported no valid return
    (0.0, NaN, inf, outside [range_min, range_max]) and beyond a scan's own beam count (N = the largest count);
    intensities (S, N): counts (0 where absent); mu_rad (S, N): each scan's own bearings
    angle_min + i * angle_increment (continued past its beam count); time_increment_s (S,): each scan's time
    between beams; beam_counts (S,): beams each scan carried. The constructor also accepts mu_rad (N,) and a
    scalar time_increment_s (the same layout for every scan) and broadcasts them. ``angle_per_scan``: the servo
    stands still while the laser scans (step and scan, lrfcal.types.sources.ServoSource.motion), so every beam's motor
    angle is the one at its scan's stamp (see :attr:`beam_times_s`).
    """

    stamps_s: FloatArray
    ranges_m: FloatArray
    intensities: FloatArray
    mu_rad: FloatArray
    time_increment_s: FloatArray
    scan_time_s: float
    range_min_m: float
    range_max_m: float
    frame_id: str = "laser"
    #: where the scans came from ("<bag>: <topic>"), for error messages; "" when unknown.
    source: str = ""
    beam_counts: IntArray = field(default_factory=lambda: _EVERY_BEAM)
    angle_per_scan: bool = False

    def __post_init__(self) -> None:
        S, N = np.shape(self.ranges_m)
        mu = np.asarray(self.mu_rad, dtype=np.float64)
        if mu.ndim == 1:
            mu = np.broadcast_to(mu, (S, N)).copy()
        ti = np.asarray(self.time_increment_s, dtype=np.float64)
        if ti.ndim == 0:
            ti = np.full(S, float(ti))
        counts = (np.full(S, N, dtype=np.int64) if self.beam_counts is None or self.beam_counts is _EVERY_BEAM
                  else np.asarray(self.beam_counts, dtype=np.int64))
        if mu.shape != (S, N) or ti.shape != (S,) or counts.shape != (S,):
            raise ValueError(f"Scans: mu_rad {mu.shape}, time_increment_s {ti.shape}, beam_counts {counts.shape} "
                             f"do not match ranges_m {(S, N)}")
        object.__setattr__(self, "mu_rad", mu)
        object.__setattr__(self, "time_increment_s", ti)
        object.__setattr__(self, "beam_counts", counts)

    @property
    def beam_times_s(self) -> FloatArray:
        """(S, N) the laser-clock time at which every beam's motor angle is taken (:meth:`angle_times_at`)."""
        S, N = self.ranges_m.shape
        return self.angle_times_at(np.arange(S)[:, None], np.arange(N)[None, :])

    def subset(self, mask: NDArray[np.bool_]) -> Scans:
        """The scans where ``mask`` (S,) is True: every per-scan array field subset, the rest kept."""
        S = mask.size
        if mask.all():
            return self
        fields: dict[str, Any] = {k: v[mask] for k, v in vars(self).items()
                                  if isinstance(v, np.ndarray) and v.ndim >= 1 and v.shape[0] == S}
        return replace(self, **fields)

    def angle_times_at(self, scan: ArrayLike, beam: ArrayLike) -> FloatArray:
        """The laser-clock time at which the motor angle of beam ``beam`` of scan ``scan`` is taken (index arrays
        that broadcast together; the result has their shape): the beam's own time, stamp + beam * time_increment,
        while the servo turns during the scan; the scan's stamp for every beam of a step-and-scan rig
        (``angle_per_scan``), whose servo stands still while it scans."""
        scan, beam = np.asarray(scan), np.asarray(beam)
        if self.angle_per_scan:
            return np.broadcast_to(self.stamps_s[scan], np.broadcast_shapes(scan.shape, beam.shape)).copy()
        return self.stamps_s[scan] + beam * np.asarray(self.time_increment_s)[scan]


@dataclass(frozen=True)
class ReadReport:
    """What the bag reader kept, skipped, masked and assumed (never a silent change); printed by
    ``lrfcal inspect`` and carried in :class:`Recording`.

    Counts are over the scan topic's messages; ``masked`` counts returns set to NaN by cause ("zero", "nan",
    "inf", "below_range_min", "above_range_max"); ``skipped`` counts dropped scans by cause ("empty",
    "bad_angle_increment", ...); clock offsets: ``*_receive_minus_stamp_s`` = median(receive - stamp) per
    topic, ``clock_offset_s`` = the coarse laser-minus-servo offset from them and ``clock_offset_applied``
    whether the reader moved the servo stamps onto the laser clock by it (when > 1 s).
    """

    bag: str = ""
    scan_source: str = ""
    servo_source: str = ""
    n_scan_messages: int = 0
    n_scans: int = 0
    n_beams: int = 0
    n_valid_returns: int = 0
    beam_count_min: int = 0
    beam_count_max: int = 0
    skipped: dict[str, int] = field(default_factory=dict)
    masked: dict[str, int] = field(default_factory=dict)
    n_time_increment_assumed: int = 0
    assumed_time_increment_s: float | None = None
    n_servo_messages: int = 0
    n_servo_samples: int = 0
    servo_skipped: dict[str, int] = field(default_factory=dict)
    scan_receive_minus_stamp_s: float | None = None
    servo_receive_minus_stamp_s: float | None = None
    clock_offset_s: float = 0.0
    clock_offset_applied: bool = False
    notes: tuple[str, ...] = ()
    #: what the reader recovered of a recording or left out of it (a bag cut short, the other side of a clock
    #: step: lrfcal.io.bag_recover, lrfcal.io.clocksteps), in words; the calibration repeats them in its notes
    left_out: tuple[str, ...] = ()

    def lines(self) -> list[str]:
        """The report as human-readable lines (counts and notes)."""
        out = [f"scans: {self.n_scans} of {self.n_scan_messages} messages on {self.scan_source}, "
               f"{self.beam_count_min}-{self.beam_count_max} beams, {self.n_valid_returns} valid of "
               f"{self.n_beams} returns"]
        if self.skipped:
            out.append("skipped scans: " + ", ".join(f"{k} {v}" for k, v in sorted(self.skipped.items())))
        if self.masked:
            out.append("masked returns: " + ", ".join(f"{k} {v}" for k, v in sorted(self.masked.items())))
        if self.n_time_increment_assumed:
            out.append(f"time_increment assumed {self.assumed_time_increment_s!r} s in "
                       f"{self.n_time_increment_assumed} scans")
        out.append(f"servo: {self.n_servo_samples} samples from {self.n_servo_messages} messages on "
                   f"{self.servo_source}" + ("" if not self.servo_skipped else " (skipped: " + ", ".join(
                       f"{k} {v}" for k, v in sorted(self.servo_skipped.items())) + ")"))
        out.append(f"clocks: laser-minus-servo offset {self.clock_offset_s:+.6f} s "
                   f"({'applied' if self.clock_offset_applied else 'not applied, below 1 s'})")
        out.extend(self.left_out)
        out.extend(self.notes)
        return out


@dataclass(frozen=True)
class JointStates:
    """The motor joint's samples: stamps_s (J,) (servo clock), positions_rad (J,) = lambda."""

    stamps_s: FloatArray
    positions_rad: FloatArray
    name: str = "servo"

    def signed(self, sign: int) -> JointStates:
        """These joint states with the servo's direction ``sign`` applied (+1: as recorded; -1: every angle negated,
        the servo turning the other way than declared): the one place the servo's sign is applied."""
        if sign > 0:
            return self
        return JointStates(stamps_s=self.stamps_s, positions_rad=-self.positions_rad, name=self.name)


@dataclass(frozen=True)
class TapeMeasurements:
    """Hand-measured marker distances: ids (n,), pairs (P, 2) indices into ids, distances_m (P,)."""

    marker_ids: tuple[str, ...]
    pairs: IntArray
    distances_m: FloatArray


@dataclass(frozen=True)
class SelfBox:
    """A part of the rig the scanner sees (its stand: a base board, an upright, the motor's housing), a box fixed to
    the motor frame M: its centre's pose in M and its edge lengths [m] along the box's own x, y, z."""

    pose: Pose
    size_m: tuple[float, float, float]


@dataclass(frozen=True)
class Nominal:
    """Design values the calibration starts from (nominal.yaml)."""

    dh: DH
    #: the design DH values' 1-sigma (a, alpha, b, beta [m, rad]; the rig file's ``dh_tolerance``; None: not declared)
    dh_tolerance: tuple[float, float, float, float] | None = None
    mount: Pose | None = None
    marker_radius_m: float = 0.005
    beam_divergence_rad: float = 0.0  # full angle: the footprint on a marker (lrfcal.model.sphere.footprint_depth)
    range_sigma_m: float | None = None  # the scanner's range noise [m] (None: not declared)
    range_pattern: bool = False  # the scanner's ranges carry an error along the scan (lrfcal.model.range_pattern)
    #: the rig's own parts the scanner sees (the rig file's ``self_boxes``): their returns are no scene
    self_boxes: tuple[SelfBox, ...] = ()
    scan_topic: str = "/scan"
    joint_topic: str = "/joint_states"
    joint_name: str = "servo"
    #: ScanSource / ServoSource (lrfcal.types.sources): where the bag keeps scans and servo angle (None: from the fields
    #: above, a LaserScan topic and a sensor_msgs/JointState joint).
    scan: ScanSource | None = None
    servo: ServoSource | None = None
    #: LogLayout (lrfcal.types.sources): how a scan log is laid out (the rig file's ``log:``; None: not given)
    log: LogLayout | None = None


@dataclass(frozen=True)
class Recording:
    """A read recording: scans (laser clock), joint states (laser clock once the reader's coarse offset is
    applied, see report.clock_offset_applied), tape distances (None when not needed, e.g. lrfcal reproject),
    nominal values, and the reader's report of what it skipped, masked and assumed."""

    scans: Scans
    joints: JointStates
    tape: TapeMeasurements | None
    nominal: Nominal
    source: Path | None = None
    report: ReadReport | None = None


def scan_spans(scans: Scans) -> tuple[FloatArray, FloatArray]:
    """(S,), (S,): laser-clock times of the first and the last beam each scan carried (beam_counts); both the
    stamp for a step-and-scan rig (Scans.angle_per_scan), whose beams all take the angle at the stamp."""
    if scans.angle_per_scan:  # step and scan: the angle of every beam is the one at the stamp
        return scans.stamps_s, scans.stamps_s
    t1 = scans.stamps_s + np.maximum(scans.beam_counts - 1, 0) * np.asarray(scans.time_increment_s)
    return np.minimum(scans.stamps_s, t1), np.maximum(scans.stamps_s, t1)


def joint_period_s(joints: JointStates) -> float:
    """Median sampling period of the joint states [s] (0 for fewer than 2 samples)."""
    if joints.stamps_s.size < 2:
        return 0.0
    return float(np.median(np.diff(joints.stamps_s)))


__all__ = ["JointStates", "Nominal", "ReadReport", "Recording", "Scans", "TapeMeasurements", "joint_period_s",
           "scan_spans"]
