"""What the rerun viewer (:mod:`lrfcal.report.viz`) and the figures (:mod:`lrfcal.report.figures`,
:mod:`lrfcal.commands.reproject`) draw,
computed from a :class:`CalibrationResult` (pure numpy; matplotlib only for the colour map, imported lazily).

Residuals (:func:`marker_returns`) go from each reprojected marker return to the nearest point on its marker sphere
(radius ``recording.nominal.marker_radius_m``) at the MarkerMap position, for any parameter set, so that before and
after are computed the same way.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.kinematics import Params, points_W
from lrfcal.model.marker import residuals_3d
from lrfcal.model.scanner import true_returns
from lrfcal.model.unknowns import core_vector
from lrfcal.result import CalibrationResult, MarkerEvidence

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def subsample_indices(n: int, max_n: int) -> IntArray:
    """Indices of an evenly strided subset of range(n) with at most max_n elements (all when n <= max_n)."""
    if n <= max_n:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, max_n).round().astype(np.int64))


def intensity_colors(intensity: ArrayLike, cmap: str = "viridis") -> NDArray[np.uint8]:
    """(Q,) intensities [counts] -> (Q, 3) uint8 RGB; log10(1 + I) scaled between its 1st and 99.5th
    percentiles."""
    import matplotlib

    x = np.log10(1.0 + np.clip(np.nan_to_num(np.asarray(intensity, dtype=float)), 0.0, None))
    if x.size == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(x, [1.0, 99.5])
    u = np.clip((x - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return (matplotlib.colormaps[cmap](u)[..., :3] * 255).astype(np.uint8)


def marker_returns(
    result: CalibrationResult, evidence: MarkerEvidence, params: Params, calibrated: bool = False
) -> tuple[FloatArray, FloatArray, IntArray, IntArray]:
    """The marker returns of ``result`` (its ``evidence``) reprojected with ``params`` and their residual vectors to
    the marker surface; ``calibrated``: with the calibration's intrinsics too (its range offset, marker range bias and
    scales, as the model applies them), else with the intrinsics at their start.

    Only observations assigned to a marker (marker >= 0) are used (K of them).
    Returns:
        points_W (K, 3) reprojected returns; to_marker_W (K, 3) vector from each return to the nearest point
        of its marker sphere (centre = MarkerMap position, radius = nominal marker radius); marker (K,);
        scan (K,).
    """
    obs = evidence.observations
    sel = obs.marker >= 0
    th = core_vector(params.dh, result.solution.intrinsic_values if calibrated else {})
    rng, lam, mu = true_returns(th, obs.ranges_m[sel], obs.lambda_rad[sel], obs.mu_rad[sel], on_marker=True)
    p = points_W(rng, lam, mu, params)
    centres = evidence.markers.positions_W[obs.marker[sel]]
    r = float(result.recording.nominal.marker_radius_m)
    to_surface = -residuals_3d(params, rng, lam, mu, centres, model="sphere", marker_radius_m=r)
    to_surface[np.linalg.norm(p - centres, axis=1) <= r] = 0.0  # inside the sphere: no arrow
    return p, to_surface, obs.marker[sel].astype(np.int64), obs.scan[sel].astype(np.int64)


def per_scan_rms_m(scan: IntArray, residual_norm_m: FloatArray, n_scans: int) -> FloatArray:
    """(S,) RMS of the residual norms of the returns of each scan; NaN for scans without marker returns."""
    ss = np.bincount(scan, weights=residual_norm_m**2, minlength=n_scans)
    cnt = np.bincount(scan, minlength=n_scans)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(ss / np.maximum(cnt, 1)), np.nan)


def motor_angle_per_scan_rad(result: CalibrationResult) -> FloatArray:
    """(S,) motor angle at the middle of each scan: joint positions interpolated at stamp + scan_time / 2.

    Ignores any laser/servo clock offset (good enough to animate the rig); falls back to the marker returns'
    lambda (nearest observed scan) when there are no joint samples, else 0.
    """
    sc = result.recording.scans
    js = result.recording.joints
    t = sc.stamps_s + 0.5 * sc.scan_time_s
    if js.stamps_s.size >= 2:
        order = np.argsort(js.stamps_s)
        return np.interp(t, js.stamps_s[order], js.positions_rad[order])
    match result.evidence:
        case MarkerEvidence(observations=obs) if len(obs) > 0:
            return np.interp(np.arange(sc.stamps_s.size), obs.scan.astype(float), obs.lambda_rad)
        case _:
            return np.zeros(sc.stamps_s.size)


__all__ = ["intensity_colors", "marker_returns", "motor_angle_per_scan_rad", "per_scan_rms_m", "subsample_indices"]
