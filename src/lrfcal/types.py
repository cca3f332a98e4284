"""Data passed between the pipeline's stages. Pure containers: no I/O, no computation beyond properties.

Array shapes: S scans, N beams per scan, J joint-state samples, n markers, P measured pairs, B blobs,
K marker returns (observations).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .kinematics import DH, Params, Pose

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class Scans:
    """All LaserScan messages of a recording, in time order.

    stamps_s (S,): header.stamp (time of beam 0, laser clock); ranges_m (S, N): NaN where the driver reported
    no valid return (NaN, inf, outside [range_min, range_max]); intensities (S, N): counts (0 where absent);
    mu_rad (N,): beam bearings angle_min + i * angle_increment.
    """

    stamps_s: FloatArray
    ranges_m: FloatArray
    intensities: FloatArray
    mu_rad: FloatArray
    time_increment_s: float
    scan_time_s: float
    range_min_m: float
    range_max_m: float
    frame_id: str = "laser"
    #: where the scans came from ("<bag>: <topic>"), for error messages; "" when unknown.
    source: str = ""

    @property
    def beam_times_s(self) -> FloatArray:
        """(S, N) time of every beam: stamp + i * time_increment."""
        return self.stamps_s[:, None] + np.arange(self.ranges_m.shape[1]) * self.time_increment_s


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
    scan_topic: str = "/scan"
    joint_topic: str = "/joint_states"
    joint_name: str = "servo"


@dataclass(frozen=True)
class Recording:
    scans: Scans
    joints: JointStates
    tape: TapeMeasurements
    nominal: Nominal
    source: Path | None = None


@dataclass(frozen=True)
class MarkerMap:
    """Stage 1: marker coordinates in W from the tape distances (MDS, then SMACOF when pairs are missing).

    positions_W (n, 3); stress: sqrt(sum w (d_ij - |x_i - x_j|)^2 / sum w d_ij^2) (normalised, unitless);
    rms_m: RMS of (d_ij - |x_i - x_j|) over the measured pairs kept; planarity: smallest / largest singular
    value of the centred coordinates (0 for a coplanar layout); dropped_pairs: the tape pairs found
    inconsistent with the others and left out of the map (gross errors, see lrfcal.mds).
    """

    marker_ids: tuple[str, ...]
    positions_W: FloatArray
    stress: float
    rms_m: float
    planarity: float
    coplanar: bool
    dropped_pairs: tuple[DroppedPair, ...] = ()


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
class Solution:
    """Stage 6: estimate, covariance (10, 10) in PARAM_NAMES order, sigma (10,), RMS of the 3D residuals,
    residuals_m (K, 3) (reprojected return minus its model point, in W), per-marker RMS (n,), status text."""

    params: Params
    covariance: FloatArray
    sigma: FloatArray
    residual_rms_m: float
    residuals_m: FloatArray
    per_marker_rms_m: FloatArray
    n_observations: int
    n_iterations: int
    status: str


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
class CalibrationResult:
    """Everything the pipeline produced, for the writers, the loop and the visualisation."""

    recording: Recording
    markers: MarkerMap
    detections: Detections
    observations: Observations
    association: Association
    start: Params
    solution: Solution
    baseline: Solution | None
    cloud_before_M: FloatArray
    cloud_after_M: FloatArray
    cloud_intensity: FloatArray
    geometry_before: TunnelGeometry | None
    geometry_after: TunnelGeometry | None
    timings_s: dict[str, float] = field(default_factory=dict)
    surfaces: tuple[Any, ...] = ()  # lrfcal.surfaces.Surface: the planes the markers are mounted on
    surface_returns: Any = None  # lrfcal.surfaces.SurfaceReturns used in the joint solve, or None
