"""A small, self-consistent synthetic :class:`CalibrationResult` for tests of the visualisation and figures.

No simulator: a box-shaped room in W (the marker frame), a handful of marker spheres on the walls, a rotating
laser with known true parameters. Every array is produced with :mod:`lrfcal.model.kinematics`, so the reprojected
marker returns sit on their markers with the true parameters and off them with the start parameters.

Shapes: S scans, N beams, n markers, B blobs, K marker returns, Q cloud points.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from lrfcal.model.kinematics import DH, Params, Pose, beam_rays_M, points_M, points_W, transform_points
from lrfcal.result import CalibrationResult, MarkerEvidence
from lrfcal.types import (
    Association,
    Blob,
    Detections,
    JointStates,
    MarkerMap,
    Nominal,
    Observations,
    Recording,
    Scans,
    Solution,
    TapeMeasurements,
    TunnelGeometry,
)

#: Half-extents of the room in W [m]: x in [-1, 2.5], y in [-1, 1], z in [-0.5, 1.8].
ROOM_MIN_W = np.array([-1.0, -1.0, -0.5])
ROOM_MAX_W = np.array([2.5, 1.0, 1.8])
#: Radius within which a beam counts as hitting a marker [m] (exaggerated so that blobs span a few pixels).
MARKER_HIT_RADIUS_M = 0.06

#: Motor axis (z of M) roughly along +x of W (pitch near 90 deg), scan plane containing the motor axis
#: (alpha near 90 deg): the scan plane rolls about the tunnel axis as in the seed paper.
TRUE = Params(Pose(0.10, 0.05, 0.30, 0.02, 1.50, 0.05), DH(0.030, 1.61, 0.060, 0.02))
START = Params(Pose(0.14, 0.01, 0.33, 0.0, 1.45, 0.0), DH(0.0, 1.5708, 0.050, 0.0))
#: What the "solver" returns: the truth plus a small error.
ESTIMATE = Params(Pose(0.101, 0.049, 0.301, 0.021, 1.501, 0.051), DH(0.0305, 1.611, 0.0598, 0.0202))


def marker_positions_W() -> np.ndarray:
    """(6, 3) true marker centres [m]: a V on the front wall and two markers on the side walls."""
    return np.array([
        [2.5, -0.40, 1.00],
        [2.5, -0.20, 0.60],
        [2.5, 0.00, 0.25],
        [2.5, 0.25, 0.65],
        [2.0, -1.0, 0.40],
        [1.2, 1.0, 0.90],
    ])


def _room_ranges(origins_W: np.ndarray, dirs_W: np.ndarray) -> np.ndarray:
    """(K,) distance from each origin along its unit direction to the inside of the axis-aligned room."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (ROOM_MAX_W - origins_W) / dirs_W
        t_lo = (ROOM_MIN_W - origins_W) / dirs_W
    t = np.where(dirs_W > 0, t_hi, t_lo)
    t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
    return t.min(axis=1)


def make_result(n_scans: int = 90, n_beams: int = 271, seed: int = 0) -> CalibrationResult:
    """Fabricate a CalibrationResult: S = n_scans scans of N = n_beams beams over +-135 deg, lambda +-90 deg.

    Returns a result whose cloud has Q = number of valid returns points (all of them: the room is closed) and
    whose observations are all returns of all detected blobs (every one assigned to a marker).
    """
    rng = np.random.default_rng(seed)
    S, N = n_scans, n_beams
    mu = np.linspace(-np.deg2rad(135.0), np.deg2rad(135.0), N)
    scan_time = 0.025
    stamps = 10.0 + np.arange(S) * 0.1
    t_inc = scan_time / 1440.0
    lam_scan = np.linspace(-np.pi / 2, np.pi / 2, S)
    lam = np.repeat(lam_scan[:, None], N, axis=1)  # (S, N): no motion during a scan
    mus = np.broadcast_to(mu, (S, N))

    T_W_M = TRUE.mount.matrix()
    o_M, d_M = beam_rays_M(lam.ravel(), mus.ravel(), TRUE.dh)
    o_W = transform_points(T_W_M, o_M)
    d_W = d_M @ T_W_M[:3, :3].T
    ranges = _room_ranges(o_W, d_W)

    markers = marker_positions_W()
    intensity = 300.0 + 30.0 * rng.standard_normal(ranges.shape)
    # marker hits: distance of each marker centre from each ray
    rel = markers[None, :, :] - o_W[:, None, :]  # (SN, n, 3)
    along = np.einsum("knj,kj->kn", rel, d_W)
    perp = np.linalg.norm(rel - along[..., None] * d_W[:, None, :], axis=2)
    hit = (perp < MARKER_HIT_RADIUS_M) & (along > 0) & (along < ranges[:, None])
    hit_any = hit.any(axis=1)
    which = np.where(hit_any, np.argmin(np.where(hit, perp, np.inf), axis=1), -1)
    k = np.flatnonzero(hit_any)
    ranges[k] = along[k, which[k]]
    intensity[k] = 20000.0 * np.exp(-((perp[k, which[k]] / MARKER_HIT_RADIUS_M) ** 2) * 2.0)
    ranges = np.round(ranges.reshape(S, N), 3)
    intensity = np.clip(intensity.reshape(S, N), 0, 65535)
    which = which.reshape(S, N)

    threshold = 2000.0
    labels, nlab = ndimage.label(intensity > threshold)
    labels = labels.astype(np.int64) - 1
    blobs = []
    for b in range(nlab):
        si, bi = np.nonzero(labels == b)
        j = int(np.argmax(intensity[si, bi]))
        blobs.append(Blob(si.astype(np.int64), bi.astype(np.int64), int(si[j]), int(bi[j]),
                          float(intensity[si[j], bi[j]])))
    detections = Detections(threshold, tuple(blobs), labels)

    # observations: every return of every blob, assigned to the marker it hit
    obs_rows = [(b, s, i) for b, bl in enumerate(blobs)
                for s, i in zip(bl.scan_idx, bl.beam_idx, strict=True)]
    ob_blob = np.array([r[0] for r in obs_rows], dtype=np.int64)
    ob_scan = np.array([r[1] for r in obs_rows], dtype=np.int64)
    ob_beam = np.array([r[2] for r in obs_rows], dtype=np.int64)
    ob_marker = which[ob_scan, ob_beam].astype(np.int64)
    is_peak = np.array([blobs[b].peak_scan == s and blobs[b].peak_beam == i for b, s, i in obs_rows])
    observations = Observations(
        blob=ob_blob, marker=ob_marker, scan=ob_scan, beam=ob_beam, ranges_m=ranges[ob_scan, ob_beam],
        mu_rad=mu[ob_beam], lambda_rad=lam[ob_scan, ob_beam], times_s=stamps[ob_scan] + ob_beam * t_inc,
        intensity=intensity[ob_scan, ob_beam], is_peak=is_peak,
    )
    blob_to_marker = np.array([int(np.bincount(ob_marker[ob_blob == b]).argmax()) for b in range(len(blobs))])

    marker_ids = tuple(f"m{i:02d}" for i in range(len(markers)))
    mds = markers + 0.002 * rng.standard_normal(markers.shape)
    n = len(markers)
    pairs = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=np.int64)
    dist = np.linalg.norm(markers[pairs[:, 0]] - markers[pairs[:, 1]], axis=1)
    marker_map = MarkerMap(marker_ids, mds, stress=0.001, rms_m=0.002, planarity=0.3, coplanar=False)

    def solution(params: Params) -> Solution:
        p = points_W(observations.ranges_m, observations.lambda_rad, observations.mu_rad, params)
        res = p - mds[ob_marker]
        per = np.array([np.sqrt(np.mean(np.sum(res[ob_marker == m] ** 2, axis=1))) if np.any(ob_marker == m)
                        else np.nan for m in range(len(markers))])
        rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
        return Solution(params, np.eye(10) * 1e-8, np.full(10, 1e-4), rms, res, per, len(p), 7, "converged")

    valid = np.isfinite(ranges)
    lam_v, mu_v, r_v = lam[valid], mus[valid], ranges[valid]
    nominal = Nominal(dh=START.dh, mount=START.mount)
    recording = Recording(
        scans=Scans(stamps, np.where(valid, ranges, np.nan), intensity, mu, t_inc, scan_time, 0.023, 60.0),
        joints=JointStates(stamps + 0.0125, lam_scan.copy()),
        tape=TapeMeasurements(marker_ids, pairs, dist),
        nominal=nominal,
    )
    geo = TunnelGeometry(2.0, 2.3, 2.4)
    return CalibrationResult(
        recording=recording,
        evidence=MarkerEvidence(
            markers=marker_map,
            detections=detections,
            observations=observations,
            association=Association(blob_to_marker, False, START.mount.matrix(), 0.02, len(blobs)),
        ),
        start=START,
        solution=solution(ESTIMATE),
        cloud_before_M=points_M(r_v, lam_v, mu_v, START.dh),
        cloud_after_M=points_M(r_v, lam_v, mu_v, ESTIMATE.dh),
        cloud_intensity=intensity[valid],
        geometry_before=geo,
        geometry_after=geo,
        timings_s={"total": 1.0},
    )
