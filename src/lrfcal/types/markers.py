"""The marker way's data: the marker map from the tape, the intensity blobs, the marker returns and their
association with the map. Array shapes: S scans, N beams, n markers, B blobs, K marker returns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.types.arrays import BoolArray, FloatArray, IntArray

#: a label image (S, N): a blob's index, -1 for background; int8 where only that sign is kept (the copy the report's
#: figures draw, lrfcal.report.figures.drawn_detections)
Labels = NDArray[np.int64] | NDArray[np.int8]


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
    labels: Labels


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


__all__ = ["Association", "Blob", "Detections", "DroppedPair", "Labels", "MarkerMap", "Observations"]
