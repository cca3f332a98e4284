"""Data passed between the pipeline's stages. Pure containers: no I/O, no computation beyond properties.

Array shapes: S scans, N beams per scan, J joint-state samples, n markers, P measured pairs, B blobs,
K marker returns (observations).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Generic, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.kinematics import DH, Params, Pose

if TYPE_CHECKING:  # the stages' own types, named here for the reader and the type checker only
    from lrfcal.estimate.normal_equations import Iteration
    from lrfcal.io.rig import LogLayout, ScanSource, ServoSource

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Scans:
    """All LaserScan messages of a recording, in time order (scans the reader skipped are not here).

    stamps_s (S,): time of beam 0 (laser clock); ranges_m (S, N): NaN where the driver reported no valid return
    (0.0, NaN, inf, outside [range_min, range_max]) and beyond a scan's own beam count (N = the largest count);
    intensities (S, N): counts (0 where absent); mu_rad (S, N): each scan's own bearings
    angle_min + i * angle_increment (continued past its beam count); time_increment_s (S,): each scan's time
    between beams; beam_counts (S,): beams each scan carried. The constructor also accepts mu_rad (N,) and a
    scalar time_increment_s (the same layout for every scan) and broadcasts them. ``angle_per_scan``: the servo
    stands still while the laser scans (step and scan, lrfcal.io.rig.ServoSource.motion), so every beam's motor
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
    beam_counts: IntArray | None = None
    angle_per_scan: bool = False

    def __post_init__(self) -> None:
        S, N = np.shape(self.ranges_m)
        mu = np.asarray(self.mu_rad, dtype=np.float64)
        if mu.ndim == 1:
            mu = np.broadcast_to(mu, (S, N)).copy()
        ti = np.asarray(self.time_increment_s, dtype=np.float64)
        if ti.ndim == 0:
            ti = np.full(S, float(ti))
        counts = (np.full(S, N, dtype=np.int64) if self.beam_counts is None
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


@dataclass(frozen=True)
class TapeMeasurements:
    """Hand-measured marker distances: ids (n,), pairs (P, 2) indices into ids, distances_m (P,)."""

    marker_ids: tuple[str, ...]
    pairs: IntArray
    distances_m: FloatArray


@dataclass(frozen=True)
class Nominal:
    """Design values the calibration starts from (nominal.yaml)."""

    dh: DH
    mount: Pose | None = None
    marker_radius_m: float = 0.005
    beam_divergence_rad: float = 0.0  # full angle: the footprint on a marker (lrfcal.model.sphere.footprint_depth)
    range_sigma_m: float | None = None  # the scanner's range noise [m] (None: not declared)
    scan_topic: str = "/scan"
    joint_topic: str = "/joint_states"
    joint_name: str = "servo"
    #: lrfcal.io.rig.ScanSource / ServoSource: where the bag keeps scans and servo angle (None: from the fields
    #: above, a LaserScan topic and a sensor_msgs/JointState joint).
    scan: ScanSource | None = None
    servo: ServoSource | None = None
    #: lrfcal.io.rig.LogLayout: how a scan log is laid out (the rig file's ``log:``; None: not given)
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


@dataclass(frozen=True)
class MarkerMap:
    """Stage 1: marker coordinates in W from the tape distances (MDS, then SMACOF when pairs are missing).

    positions_W (n, 3); stress: sqrt(sum w (d_ij - |x_i - x_j|)^2 / sum w d_ij^2) (normalised, unitless);
    rms_m: RMS of (d_ij - |x_i - x_j|) over the measured pairs kept; planarity: smallest / largest singular
    value of the centred coordinates (0 for a coplanar layout); dropped_pairs: the tape pairs found
    inconsistent with the others and left out of the map (gross errors, see lrfcal.stages.mds); covariance (3n, 3n):
    of positions_W.ravel() from the tape noise ``tape_sigma_m`` (lrfcal.stages.mds.map_covariance; None: taken as
    exact).
    """

    marker_ids: tuple[str, ...]
    positions_W: FloatArray
    stress: float
    rms_m: float
    planarity: float
    coplanar: bool
    dropped_pairs: tuple[DroppedPair, ...] = ()
    covariance: FloatArray | None = None
    tape_sigma_m: float = float("nan")


@dataclass(frozen=True)
class DroppedPair:
    """A tape pair left out of the marker map: marker ids, the measured distance, the distance the other pairs
    put it at (leave-one-out prediction), and that difference in units of the tape noise (z)."""

    id_i: str
    id_j: str
    measured_m: float
    predicted_m: float
    z: float

    @property
    def error_m(self) -> float:
        """measured - predicted."""
        return self.measured_m - self.predicted_m


@dataclass(frozen=True)
class Blob:
    """Stage 2: one connected component of above-threshold returns in the (scan, beam) intensity image.

    scan_idx (k,), beam_idx (k,): its pixels; peak_scan, peak_beam: the pixel of maximum intensity (the
    paper's observation).
    """

    scan_idx: IntArray
    beam_idx: IntArray
    peak_scan: int
    peak_beam: int
    peak_intensity: float

    @property
    def size(self) -> int:
        return int(self.scan_idx.size)


@dataclass(frozen=True)
class Detections:
    """Stage 2 output: threshold (counts), blobs, and the label image (S, N) int (-1 background)."""

    threshold: float
    blobs: tuple[Blob, ...]
    labels: IntArray


@dataclass(frozen=True)
class Observations:
    """Marker returns fed to the solver, one row per return (K rows).

    blob (K,): index into Detections.blobs; marker (K,): index into MarkerMap (-1 unassigned); scan, beam (K,);
    ranges_m, mu_rad, lambda_rad (K,): range, beam bearing and the motor angle at the beam's own time;
    times_s (K,) beam time on the laser clock; intensity (K,); is_peak (K,): the blob's max-intensity return.
    """

    blob: IntArray
    marker: IntArray
    scan: IntArray
    beam: IntArray
    ranges_m: FloatArray
    mu_rad: FloatArray
    lambda_rad: FloatArray
    times_s: FloatArray
    intensity: FloatArray
    is_peak: BoolArray

    def subset(self, mask: NDArray[np.bool_]) -> Observations:
        return Observations(**{k: getattr(self, k)[mask] for k in self.__dataclass_fields__})

    def __len__(self) -> int:
        return int(self.ranges_m.size)


@dataclass(frozen=True)
class Association:
    """Stage 4: blob_to_marker (B,) index into MarkerMap or -1; mirrored: MDS frame was reflected to match the
    handedness of the data (MarkerMap positions are returned already un-mirrored); T_W_M (4, 4): the rigid
    transform found by the alignment (start of stage 6); rms_m: alignment RMS over matched blobs."""

    blob_to_marker: IntArray
    mirrored: bool
    T_W_M: FloatArray
    rms_m: float
    n_matched: int


@dataclass(frozen=True)
class Spread:
    """What the covariance of the difference of two solutions of overlapping data is made of (lrfcal.estimate.checks):
    each
    cluster's id (C,) and influence (J^T J)^-1 J_c^T r_c over the core unknowns (C, N_CORE), and the statistical
    covariance max(s^2, 1) (J^T J)^-1 (N_CORE, N_CORE), before any widening (NaN where held or with rank loss)."""

    ids: NDArray[np.int64]
    influence: FloatArray
    statistical: FloatArray


@dataclass(frozen=True)
class Solution:
    """Stage 6: the estimate and its uncertainty.

    covariance (10, 10) and sigma (10,) in kinematics.ESTIMATE_NAMES order (x, y, z, the mount rotation as a
    rotation vector rx, ry, rz in frame M, a, alpha, b, beta; NaN for parameters held fixed, inf where the data do
    not determine them); residual_rms_m: RMS of the 3D residuals of the returns kept; residuals_m (K, 3): reprojected
    return minus its model point in W; per-marker RMS (n,); clock offset (laser stamp - servo stamp) and its sigma
    (NaN when held); information (k, k): the marginal information over ``information_names`` (the estimated core
    unknowns, lrfcal.model.unknowns.CORE_NAMES); chi (K,): whitened residual per return (NaN for unused rows);
    inlier (K,): returns kept; lambda_rad (K,): the motor angle of each return at the estimated clock offset."""

    params: Params
    covariance: FloatArray
    sigma: FloatArray
    residual_rms_m: float
    residuals_m: FloatArray
    per_marker_rms_m: FloatArray
    n_observations: int
    n_iterations: int
    status: str
    clock_offset_s: float = 0.0
    clock_offset_sigma_s: float = float("nan")
    information: FloatArray | None = None
    information_names: tuple[str, ...] = ()
    reduced_chi2: float = float("nan")
    converged: bool = True
    chi: FloatArray | None = None
    inlier: BoolArray | None = None
    lambda_rad: FloatArray | None = None
    n_surface_returns: int = 0
    #: every intrinsic of the rig model (lrfcal.model.unknowns.INTRINSICS): name -> (value, sigma; NaN when held)
    intrinsics: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: every unknown held by default that this solve held: name -> (the value one Gauss-Newton step with it freed
    #: reaches, its 1-sigma) (lrfcal.estimate.solve's score test)
    held_score: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: (10, 3n): how the estimate moves with the marker map's coordinates (lrfcal.estimate.covariance.uncertainty); the
    #: covariance holds the map's part, G C_map G^T (None: the map was taken as exact)
    map_sensitivity: FloatArray | None = None
    #: each cluster's influence and the statistical covariance (Spread, lrfcal.estimate.covariance), for the second
    #: opinion's
    #: covariance of the difference of two solutions (lrfcal.estimate.checks.difference_covariance); None with rank loss
    spread: Spread | None = None
    #: each accepted Levenberg-Marquardt iteration of every pass (lrfcal.estimate.engine.Estimate.log)
    iterations: tuple[Iteration, ...] = ()

    def with_dh_systematic(self, d: ArrayLike) -> Solution:
        """This solution with its DH covariance widened by d d^T, d (4,) a model error in (a, alpha, b, beta) that
        the noise's sigma does not hold (two defensible models or rounds that differ by d)."""
        d = np.asarray(d, dtype=float)
        cov = np.array(self.covariance, dtype=float)
        cov[6:10, 6:10] += np.outer(d, d)
        return replace(self, covariance=cov, sigma=np.sqrt(np.clip(np.diag(cov), 0.0, None)))

    @property
    def intrinsic_values(self) -> dict[str, float]:
        """The intrinsics' values by name, estimated or held (what lrfcal.model.unknowns.core_vector takes)."""
        return {name: value for name, (value, _) in self.intrinsics.items()}

    @property
    def range_offset_m(self) -> float:
        """Added to every reported range (estimated with estimate_range_bias; 0 when held)."""
        return self.intrinsics.get("range_offset", (0.0, math.nan))[0]

    @property
    def range_offset_sigma_m(self) -> float:
        """Its 1-sigma, NaN when held."""
        return self.intrinsics.get("range_offset", (0.0, math.nan))[1]

    @property
    def marker_range_bias_m(self) -> float:
        """Added to the ranges of marker returns only."""
        return self.intrinsics.get("marker_range_bias", (0.0, math.nan))[0]

    @property
    def marker_range_bias_sigma_m(self) -> float:
        """Its 1-sigma, NaN when held."""
        return self.intrinsics.get("marker_range_bias", (0.0, math.nan))[1]


@dataclass(frozen=True)
class Plane:
    """A fitted plane n . p = d (n unit, in frame M), its label and inlier count."""

    normal: FloatArray
    offset_m: float
    label: str
    n_inliers: int


@dataclass(frozen=True)
class TunnelGeometry:
    """Stage 8: dimensions from RANSAC planes (paper Table III); None where a plane was not found."""

    width_m: float | None
    height_m: float | None
    plate_distance_m: float | None
    planes: tuple[Plane, ...] = field(default=())


@dataclass(frozen=True)
class Check:
    """One consistency check of the result: its name, whether it passed, and the numbers."""

    name: str
    passed: bool
    detail: str


T = TypeVar("T")


@dataclass(frozen=True)
class Noted(Generic[T]):
    """A stage's result ``value`` with its ``notes``: what it assumed, trimmed or dropped, in words, in the order
    they arose (the way and the orchestrator collect them into CalibrationResult.notes)."""

    value: T
    notes: tuple[str, ...] = ()
