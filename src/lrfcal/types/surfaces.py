"""The planes a calibration observes: the surfaces the markers sit on (in W) and their returns, the scene's
planes (in M) the targetless way segments, and the tunnel's planes and dimensions. K2 surface returns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from lrfcal.types.arrays import FloatArray, IntArray


@dataclass(frozen=True)
class Surface:
    """A marker-carrying plane in W: n . p = offset_m (n unit, pointing away from the sensor), its markers, and
    the markers' extent in the plane (2 axes (2, 3), centre (3,), lower/upper bounds (2,) in m).

    prior_sigma (3,): how well the markers fix the plane: tilts (rad) towards axes[0] and axes[1], and the
    offset (m). The solver treats the plane as a nuisance with this prior, not as exactly known.
    prior_jacobian (3, 3n): how the prior's mean (those tilts and the offset) moves with the n markers' coordinates
    (lrfcal.stages.surfaces.plane_prior_jacobian; None when the plane is not the markers'), for the marker map's own
    uncertainty.
    """

    normal: FloatArray
    offset_m: float
    marker_idx: IntArray
    axes: FloatArray
    centre: FloatArray
    lower: FloatArray
    upper: FloatArray
    prior_sigma: FloatArray
    prior_jacobian: FloatArray | None = None


@dataclass(frozen=True)
class SurfaceReturns:
    """Non-marker returns on the surfaces (K2 rows): scan, beam indices; lambda_rad, mu_rad, ranges_m; the
    surface index of each; normals (K2, 3) and offsets (K2,) of their planes in W; times_s (K2,) their beam times
    on the laser clock (None when unknown)."""

    scan: IntArray
    beam: IntArray
    lambda_rad: FloatArray
    mu_rad: FloatArray
    ranges_m: FloatArray
    surface: IntArray
    normals: FloatArray
    offsets_m: FloatArray
    times_s: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.ranges_m.size)

    def subset(self, mask: NDArray[np.bool_]) -> SurfaceReturns:
        return SurfaceReturns(self.scan[mask], self.beam[mask], self.lambda_rad[mask], self.mu_rad[mask],
                              self.ranges_m[mask], self.surface[mask], self.normals[mask], self.offsets_m[mask],
                              None if self.times_s is None else self.times_s[mask])

    def joined(self, other: SurfaceReturns) -> SurfaceReturns:
        """These returns followed by ``other``'s (their surface indices kept; beam times where both have them)."""
        a, b, cat = self, other, np.concatenate
        return SurfaceReturns(cat([a.scan, b.scan]), cat([a.beam, b.beam]), cat([a.lambda_rad, b.lambda_rad]),
                              cat([a.mu_rad, b.mu_rad]), cat([a.ranges_m, b.ranges_m]), cat([a.surface, b.surface]),
                              cat([a.normals, b.normals]), cat([a.offsets_m, b.offsets_m]),
                              None if a.times_s is None or b.times_s is None else cat([a.times_s, b.times_s]))


@dataclass(frozen=True)
class ScenePlane:
    """A plane of the scene in frame M: n . p = offset_m (n unit, pointing away from the motor axis' origin), the
    number of points assigned to it, their RMS distance from it (m) and their centroid (3,)."""

    normal: FloatArray
    offset_m: float
    n_points: int
    rms_m: float
    centroid: FloatArray


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


__all__ = ["Plane", "ScenePlane", "Surface", "SurfaceReturns", "TunnelGeometry"]
