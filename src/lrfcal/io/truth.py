"""A simulator's ground truth in the calibration's frame: the alignment of the truth's world to the marker frame W.

Used by the report (the truth and the errors of every parameter), by lrfcal.commands.calibrate (the nominal mount and
the true markers in W for the figures and rerun) and by lrfsim.compare (Tables I and III); it needs no simulator:
``truth`` is the plain content of ground_truth.yaml (:func:`truth_dict`).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import DH, DH_NAMES, MOUNT_NAMES, Pose, homogeneous, points_M, transform_points
from lrfcal.result import CalibrationResult, MarkerEvidence

FloatArray = NDArray[np.float64]


def _kabsch(A: FloatArray, B: FloatArray) -> tuple[FloatArray, float]:
    """Proper rigid T (4, 4) minimising sum |T a_i - b_i|^2 over (n, 3) point sets, and its RMS [m]."""
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(Vt.T @ U.T))) or 1.0])
    R = Vt.T @ D @ U.T
    T = homogeneous(R, cb - R @ ca)
    rms = float(np.sqrt(np.mean(np.sum((A @ R.T + T[:3, 3] - B) ** 2, axis=1))))
    return T, rms


def align_truth_frame(positions_W: FloatArray, marker_ids: tuple[str, ...], truth_markers: dict[str, Any],
                      tol_m: float = 0.01) -> tuple[FloatArray, str] | None:
    """T_W_sim (4, 4) aligning the truth's marker positions (simulator frame) to the marker map in W.

    First by marker id (proper rigid fit). If that fails but a reflection fits -- a mirror-symmetric layout
    (e.g. the same V on both walls) lets the map come out mirrored with the ids swapped across the symmetry --
    the reflection is composed with reflections about the layout's principal planes and refined with
    nearest-neighbour correspondences. Returns (T_W_sim, how) or None when no fit is within ``tol_m`` RMS.
    """
    ids = [i for i in marker_ids if i in truth_markers]
    if len(ids) < 3:
        return None
    A = np.array([truth_markers[i] for i in ids], dtype=float).reshape(-1, 3)
    B = np.asarray(positions_W, dtype=float)[[marker_ids.index(i) for i in ids]]
    T, rms = _kabsch(A, B)
    if rms < tol_m:
        return T, "by marker id"
    ca, cb = A.mean(0), B.mean(0)
    U, _, Vt = np.linalg.svd((A - ca).T @ (B - cb))
    R_imp = Vt.T @ U.T  # the unconstrained (possibly improper) fit
    _, _, axes = np.linalg.svd(A - ca)
    best: tuple[float, FloatArray] | None = None
    for v in axes:
        R = R_imp @ (np.eye(3) - 2.0 * np.outer(v, v))
        if np.linalg.det(R) < 0:
            continue
        T = homogeneous(R, cb - R @ ca)
        for _ in range(4):
            X = A @ T[:3, :3].T + T[:3, 3]
            nn = np.argmin(np.linalg.norm(X[:, None] - B[None], axis=2), axis=1)
            if np.unique(nn).size != nn.size:
                break
            T, rms = _kabsch(A, B[nn])
        else:
            if best is None or rms < best[0]:
                best = (rms, T)
    if best is not None and best[0] < tol_m:
        return best[1], "by geometry (marker ids mirrored across the layout's symmetry)"
    return None


def truth_dict(truth: Any) -> dict[str, Any]:
    """A ground truth object (attributes dh, mount, tunnel, markers; e.g. lrfsim.compare.Truth) as the plain
    values the writers take."""
    return {
        "dh": truth.dh.as_dict(),
        "mount": truth.mount.as_dict(),
        "tunnel": truth.tunnel,
        "markers": {k: [float(x) for x in v] for k, v in truth.markers.items()},
    }


def truth_frame(result: CalibrationResult, truth: dict[str, Any], gate_m: float = 0.05
                ) -> tuple[FloatArray, str] | None:
    """T_W_sim (4, 4) mapping the simulator's world into the calibration's marker frame W, and how it was found.

    From the marker correspondence the calibration used, never from a guess at the handedness: every matched
    return, reprojected with the TRUE DH and mount (``truth``: "dh", "mount", "markers" as in ground_truth.yaml)
    and the motor angle the calibration used, lands on the physical marker it came from; each marker of the map
    is paired with the true marker most of its returns land on (within ``gate_m``), and a proper rigid fit of
    those pairs gives T_W_sim. Falls back to :func:`align_truth_frame` (by marker id) when the returns do not
    land on true markers (e.g. a calibration that took the wrong servo direction under --force).
    """
    if not isinstance(result.evidence, MarkerEvidence):  # targetless: no marker frame W
        return None
    ev = result.evidence
    markers = truth.get("markers") or {}
    ids = list(markers)
    if truth.get("dh") and truth.get("mount") and len(ids) >= 3 and len(ev.observations):
        true_W = np.array([markers[i] for i in ids], dtype=float).reshape(-1, 3)
        dh = DH(**{k: float(truth["dh"][k]) for k in DH_NAMES})
        T_sim_M = Pose(**{k: float(truth["mount"][k]) for k in MOUNT_NAMES}).matrix()
        obs = ev.observations
        lam = obs.lambda_rad if result.solution.lambda_rad is None else result.solution.lambda_rad
        radius = result.recording.nominal.marker_radius_m
        p = transform_points(T_sim_M, points_M(obs.ranges_m + radius, lam, obs.mu_rad, dh))
        d = np.linalg.norm(p[:, None, :] - true_W[None], axis=2)
        nearest = np.argmin(d, axis=1)
        near = d[np.arange(len(p)), nearest] < gate_m
        pairs = []
        for k in np.unique(obs.marker[near]):
            votes = np.bincount(nearest[near & (obs.marker == k)], minlength=len(ids))
            if votes.max() > 0.5 * votes.sum():
                pairs.append((int(k), int(np.argmax(votes))))
        if len(pairs) >= 3:
            A = true_W[[j for _, j in pairs]]
            B = np.asarray(ev.markers.positions_W, dtype=float)[[k for k, _ in pairs]]
            T, rms = _kabsch(A, B)
            if rms < 0.01:
                return T, f"by the markers the calibration's returns came from ({len(pairs)} markers)"
    return align_truth_frame(np.asarray(ev.markers.positions_W), ev.markers.marker_ids, markers)


__all__ = ["align_truth_frame", "truth_dict", "truth_frame"]
