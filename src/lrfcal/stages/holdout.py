"""The held-out check of a targetless calibration: returns the fit never used must come out no thicker.

Every HOLDOUT_EVERY-th scan is left out of the targetless fit (lrfcal.stages.targetless). After the fit, those scans'
returns are reprojected with the nominal and with the calibrated DH parameters; the scene's planes are segmented
once, in the nominal cloud (lrfcal.stages.planes.segment_planes: a segmentation that, if anything, favours the nominal),
and each plane's thickness is measured in both clouds as the robust scale (1.4826 x the median absolute
deviation) of its points' distances from their own least-squares plane. The calibration must not make the
held-out planes thicker than the nominal beyond their noise: a result the data it did not use contradict (the
URG-04LX recording whose fit gave alpha 11 deg from the authors' value while its planes got thicker, issue 20) is
refused, not written.

The noise of the pooled thickness is taken as 1.1 t / sqrt(n / 4) (the standard error of a robust scale, n / 4
effective points for a range noise correlated over neighbouring beams); the limit is 3 of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.stages import planes

FloatArray = NDArray[np.float64]

#: every HOLDOUT_EVERY-th scan (index % HOLDOUT_EVERY == HOLDOUT_EVERY - 1) is held out of the fit
HOLDOUT_EVERY = 5
#: the held-out returns used for the check, at most (an even subsample)
HOLDOUT_RETURNS = 40000
#: the fewest held-out returns on planes for the check to say anything
MIN_RETURNS = 500


def held_out_scans(n_scans: int) -> NDArray[np.bool_]:
    """(S,) True for the scans held out of the fit: every HOLDOUT_EVERY-th, spread over every pass."""
    return np.arange(n_scans) % HOLDOUT_EVERY == HOLDOUT_EVERY - 1


@dataclass(frozen=True)
class HeldOut:
    """The held-out planes' pooled thickness [m] with the nominal and the calibrated DH, the limit on its growth
    [m], and what it was measured on (returns on planes, planes)."""

    thickness_nominal_m: float
    thickness_calibrated_m: float
    limit_m: float
    n_returns: int
    n_planes: int

    @property
    def available(self) -> bool:
        return self.n_returns >= MIN_RETURNS and math.isfinite(self.thickness_nominal_m)

    @property
    def passed(self) -> bool:
        """Not thicker than the nominal by more than the limit (or nothing to judge)."""
        return not self.available or self.thickness_calibrated_m <= self.thickness_nominal_m + self.limit_m

    def detail(self) -> str:
        """One line for the report and the refusal."""
        if not self.available:
            return (f"not available: {self.n_returns} held-out returns on planes segmented in the nominal cloud "
                    f"(need {MIN_RETURNS})")
        change = self.thickness_calibrated_m - self.thickness_nominal_m
        text = (f"every {HOLDOUT_EVERY}th scan left out of the fit: its {self.n_returns} returns on "
                f"{self.n_planes} planes are {self.thickness_nominal_m * 1000:.2f} mm thick with the nominal DH, "
                f"{self.thickness_calibrated_m * 1000:.2f} mm with the calibrated ({change * 1000:+.2f} mm; limit "
                f"+{self.limit_m * 1000:.2f} mm)")
        if not self.passed:
            text += (": the calibration makes planes it did not use thicker (a scene too poor in planes of "
                     "different orientations, or a model that does not fit this rig)")
        return text


def _robust_thickness(points: FloatArray) -> float:
    """1.4826 x the median absolute deviation of the points' (P, 3) distances from their least-squares plane."""
    n, off, _ = planes.fit_plane(points)
    d = points @ n - off
    return float(1.4826 * np.median(np.abs(d - np.median(d))))


def held_out_flatness(points_nominal_M: FloatArray, points_calibrated_M: FloatArray,
                      thickness_m: float) -> HeldOut:
    """The held-out returns reprojected with the nominal (P, 3) and with the calibrated DH (P, 3), the same returns
    in the same order; ``thickness_m``: the segmentation's inlier half-width (as the fit's first round)."""
    labels, found = planes.segment_planes(points_nominal_M, thickness_m=thickness_m)
    counts, t_nom, t_cal = [], [], []
    for j in range(len(found)):
        m = labels == j
        if m.sum() >= 50:
            counts.append(int(m.sum()))
            t_nom.append(_robust_thickness(points_nominal_M[m]))
            t_cal.append(_robust_thickness(points_calibrated_M[m]))
    n = int(sum(counts))
    if n == 0:
        return HeldOut(math.nan, math.nan, math.nan, 0, 0)
    w = np.asarray(counts, dtype=float) / n
    before, after = float(w @ np.asarray(t_nom)), float(w @ np.asarray(t_cal))
    limit = 3.0 * 1.1 * before / math.sqrt(n / 4.0)
    return HeldOut(before, after, limit, n, len(counts))


__all__ = ["HOLDOUT_EVERY", "HOLDOUT_RETURNS", "HeldOut", "held_out_flatness", "held_out_scans"]
