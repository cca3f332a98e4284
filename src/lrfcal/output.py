"""Writers of a calibration: calibration.yaml, rig.urdf, the clouds (PLY) and the Markdown report.

``write_calibration`` builds the whole output folder in a temporary folder beside it and renames it into place
when complete, so a reader never sees a partial result and a failure leaves nothing behind.

Frames: W is the marker frame (from the tape distances), M the motor frame; the URDF chain is
world (= W) -> motor_base -> [servo, revolute about z] -> motor (= M') -> laser (= L', the LaserScan frame).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from xml.sax.saxutils import quoteattr

import numpy as np
import yaml
from numpy.typing import NDArray

from .errors import InputError
from .model.kinematics import (
    ANGLE_NAMES,
    DH,
    DH_NAMES,
    ESTIMATE_NAMES,
    MOUNT_NAMES,
    PARAM_NAMES,
    Params,
    Pose,
    homogeneous,
    rot_x,
    rot_z,
)
from .reproject import current_umask, write_ply
from .types import CalibrationResult, Solution, TunnelGeometry

FloatArray = NDArray[np.float64]

FORMAT_VERSION = 1
TUNNEL_KEYS = ("width_m", "height_m", "plate_distance_m")


# --- small helpers --------------------------------------------------------------------------------------------

def _f(v: Any) -> float | None:
    """A plain float for YAML, None for NaN/inf/None."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def dh_matrix(dh: DH) -> FloatArray:
    """(4, 4) T_M'_L' = Tx(a) Rx(alpha) Tz(b) Rz(beta): the fixed transform from the turning motor frame to the
    laser frame (eq. (3) without Rz(lambda) and Rz(mu))."""
    Tx = homogeneous(np.eye(3), [dh.a, 0.0, 0.0])
    Rx = homogeneous(rot_x(dh.alpha), np.zeros(3))
    Tz = homogeneous(np.eye(3), [0.0, 0.0, dh.b])
    Rz = homogeneous(rot_z(dh.beta), np.zeros(3))
    return Tx @ Rx @ Tz @ Rz


def param_sigma(solution: Solution, name: str) -> float | None:
    """1-sigma of a parameter by name (ESTIMATE_NAMES: x, y, z, rx, ry, rz, a, alpha, b, beta); None for roll,
    pitch and yaw, which are an output format whose sigma would come from the Euler angles' singularity."""
    if name not in ESTIMATE_NAMES:
        return None
    s = np.asarray(solution.sigma, dtype=float).reshape(-1)
    i = ESTIMATE_NAMES.index(name)
    return _f(s[i]) if i < s.size else None


def _solution_dict(sol: Solution) -> dict[str, Any]:
    """DH and mount (value and 1-sigma each; the rotation's uncertainty as the 1-sigma and covariance of a rotation
    vector in frame M, roll/pitch/yaw as values only), clock offset, residual RMS, returns used, solver status."""
    values = sol.params.as_dict()
    cov = np.asarray(sol.covariance, dtype=float)
    return {
        "dh": {n: {"value": _f(values[n]), "sigma": param_sigma(sol, n)} for n in DH_NAMES},
        "mount": {n: ({"value": _f(values[n]), "sigma": param_sigma(sol, n)} if n in "xyz" else
                      {"value": _f(values[n])}) for n in MOUNT_NAMES},
        "mount_rotation_sigma_rad": {n: param_sigma(sol, n) for n in ("rx", "ry", "rz")},
        "covariance": {"names": list(ESTIMATE_NAMES),
                       "matrix": [[_f(v) for v in row] for row in cov] if cov.shape == (10, 10) else None},
        "clock_offset_s": {"value": _f(sol.clock_offset_s), "sigma": _f(sol.clock_offset_sigma_s)},
        "range_offset_m": {"value": _f(sol.range_offset_m), "sigma": _f(sol.range_offset_sigma_m)},
        "marker_range_bias_m": {"value": _f(sol.marker_range_bias_m), "sigma": _f(sol.marker_range_bias_sigma_m)},
        "residual_rms_m": _f(sol.residual_rms_m),
        "n_observations": int(sol.n_observations),
        "reduced_chi2": _f(sol.reduced_chi2),
        "status": str(sol.status),
    }


def _geometry_dict(g: TunnelGeometry | None) -> dict[str, Any] | None:
    if g is None:
        return None
    return {
        "width_m": _f(g.width_m),
        "height_m": _f(g.height_m),
        "plate_distance_m": _f(g.plate_distance_m),
        "planes": [{"label": p.label, "normal": [float(x) for x in p.normal], "offset_m": float(p.offset_m),
                    "n_inliers": int(p.n_inliers)} for p in g.planes],
    }


def _marker_counts(result: CalibrationResult) -> FloatArray:
    assert result.markers is not None and result.observations is not None
    n = len(result.markers.marker_ids)
    m = np.asarray(result.observations.marker, dtype=np.int64)
    return np.bincount(m[m >= 0], minlength=n)[:n]


# --- calibration.yaml -----------------------------------------------------------------------------------------

def calibration_dict(result: CalibrationResult) -> dict[str, Any]:
    """The content of calibration.yaml (plain Python types; NaN -> None)."""
    sol = result.solution
    out: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "method": result.method,
        "units": "m, rad; frames: W marker frame (tape distances), M motor frame; T_W_M = mount",
        **_solution_dict(sol),
        "n_iterations": int(sol.n_iterations),
    }
    out.update(_marker_dict(result) if result.method == "markers" else _targetless_dict(result))
    out.update({
        "checks": [{"name": c.name, "passed": bool(c.passed), "detail": c.detail} for c in result.checks],
        "notes": list(result.notes),
        "servo_sign": int(result.servo_sign),
        "start": {k: float(v) for k, v in result.start.as_dict().items()},
        "baseline": None,
        "tunnel": {"before": _geometry_dict(result.geometry_before), "after": _geometry_dict(result.geometry_after)},
        "timings_s": {str(k): _f(v) for k, v in result.timings_s.items()},
    })
    if result.baseline is not None:
        out["baseline"] = {
            "method": "seed paper: blob peaks only, one motor angle per scan",
            **_solution_dict(result.baseline),
        }
    return out


def _targetless_dict(result: CalibrationResult) -> dict[str, Any]:
    """A targetless calibration's own keys: no world frame (mount null), the parameters held at nominal, and the
    scene's planes with their thickness before and after."""
    fit = result.plane_fit
    return {
        "units": "m, rad; frame M (motor frame): without markers there is no world frame",
        "mount": None,
        "mount_rotation_sigma_rad": None,
        "held_at_nominal": list(fit.held),
        "planes": [
            {"normal_M": [float(v) for v in p.normal], "offset_m": float(p.offset_m), "n_returns": int(n),
             "thickness_rms_m": {"before": _f(b), "after": _f(a)}}
            for p, n, b, a in zip(fit.planes, fit.n_returns, fit.rms_before_m, fit.rms_after_m, strict=True)
        ],
    }


def _marker_dict(result: CalibrationResult) -> dict[str, Any]:
    """A marker calibration's own keys: markers used, the marker map, the association, the marker surfaces."""
    assert result.markers is not None and result.detections is not None and result.association is not None
    sol = result.solution
    ids = result.markers.marker_ids
    counts = _marker_counts(result)
    per = np.asarray(sol.per_marker_rms_m, dtype=float).reshape(-1)
    return {
        "markers": {
            "used": [ids[i] for i in range(len(ids)) if counts[i] > 0],
            "unused": [ids[i] for i in range(len(ids)) if counts[i] == 0],
            "n_returns": {ids[i]: int(counts[i]) for i in range(len(ids))},
            "residual_rms_m": {ids[i]: _f(per[i]) if i < per.size else None for i in range(len(ids))},
        },
        "marker_map": {
            "stress": _f(result.markers.stress),
            "rms_m": _f(result.markers.rms_m),
            "planarity": _f(result.markers.planarity),
            "coplanar": bool(result.markers.coplanar),
            "dropped_pairs": [  # tape pairs inconsistent with the others (gross errors), left out
                {"pair": [p.id_i, p.id_j], "measured_m": _f(p.measured_m), "predicted_m": _f(p.predicted_m),
                 "z": _f(p.z)}
                for p in result.markers.dropped_pairs
            ],
        },
        "association": {
            "n_blobs": len(result.detections.blobs),
            "n_matched": int(result.association.n_matched),
            "mirrored": bool(result.association.mirrored),
            "rms_m": _f(result.association.rms_m),
        },
        "surfaces": [  # the planes the markers sit on, solved jointly (stage 6b)
            {
                "markers": [ids[int(i)] for i in srf.marker_idx],
                "normal": [float(v) for v in srf.normal],
                "offset_m": float(srf.offset_m),
                "n_returns": int(np.sum(result.surface_returns.surface == k)) if result.surface_returns else 0,
            }
            for k, srf in enumerate(result.surfaces)
        ],
        "detection_threshold": _f(result.detections.threshold),
    }


# --- rig.urdf -------------------------------------------------------------------------------------------------

def _xyz_rpy(T: FloatArray) -> tuple[str, str]:
    p = Pose.from_matrix(T)
    fmt = "{:.9g} {:.9g} {:.9g}".format
    return fmt(p.x, p.y, p.z), fmt(p.roll, p.pitch, p.yaw)


def urdf_snippet(params: Params, robot_name: str = "rotating_lrf") -> str:
    """A URDF with links world/motor_base/motor/laser: a fixed joint world -> motor_base (identity; re-parent it
    onto your robot), the revolute joint ``servo`` (axis z) whose origin is the mount pose T_W_M, and the fixed
    joint ``laser_mount`` motor -> laser whose origin is Tx(a) Rx(alpha) Tz(b) Rz(beta)."""
    mxyz, mrpy = _xyz_rpy(params.mount.matrix())
    lxyz, lrpy = _xyz_rpy(dh_matrix(params.dh))
    d = params.dh
    return f"""<?xml version="1.0"?>
<robot name={quoteattr(robot_name)}>
  <!-- generated by lrfcal: DH a={d.a:.9g} m, alpha={d.alpha:.9g} rad, b={d.b:.9g} m, beta={d.beta:.9g} rad -->
  <link name="world"/>
  <link name="motor_base"/>
  <link name="motor"/>
  <link name="laser"/>
  <joint name="world_to_motor_base" type="fixed">
    <parent link="world"/>
    <child link="motor_base"/>
    <origin xyz="0 0 0" rpy="0 0 0"/>
  </joint>
  <joint name="servo" type="revolute">
    <parent link="motor_base"/>
    <child link="motor"/>
    <origin xyz="{mxyz}" rpy="{mrpy}"/>
    <axis xyz="0 0 1"/>
    <limit lower="{-math.pi:.9g}" upper="{math.pi:.9g}" effort="10" velocity="10"/>
  </joint>
  <joint name="laser_mount" type="fixed">
    <parent link="motor"/>
    <child link="laser"/>
    <origin xyz="{lxyz}" rpy="{lrpy}"/>
  </joint>
</robot>
"""


# --- report.md ------------------------------------------------------------------------------------------------

def _disp(name: str, v: float | None) -> str:
    """Value in display units: mm for lengths, deg for angles."""
    if v is None or not math.isfinite(v):
        return "-"
    return f"{math.degrees(v):.3f}" if name in ANGLE_NAMES else f"{v * 1000:.2f}"


def _unit(name: str) -> str:
    return "deg" if name in ANGLE_NAMES else "mm"


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
    if result.markers is None or result.observations is None:  # targetless: no marker frame W
        return None
    from .model.kinematics import points_M, transform_points

    markers = truth.get("markers") or {}
    ids = list(markers)
    if truth.get("dh") and truth.get("mount") and len(ids) >= 3 and len(result.observations):
        true_W = np.array([markers[i] for i in ids], dtype=float).reshape(-1, 3)
        dh = DH(**{k: float(truth["dh"][k]) for k in DH_NAMES})
        T_sim_M = Pose(**{k: float(truth["mount"][k]) for k in MOUNT_NAMES}).matrix()
        obs = result.observations
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
            B = np.asarray(result.markers.positions_W, dtype=float)[[k for k, _ in pairs]]
            T, rms = _kabsch(A, B)
            if rms < 0.01:
                return T, f"by the markers the calibration's returns came from ({len(pairs)} markers)"
    return align_truth_frame(np.asarray(result.markers.positions_W), result.markers.marker_ids, markers)


def _truth_params(result: CalibrationResult, truth: dict[str, Any]) -> tuple[dict[str, float | None], str]:
    """Truth in PARAM_NAMES, the mount re-expressed in the marker frame W when the truth's markers allow
    aligning the simulator frame to W (else None for the mount); and a note on how (or why not)."""
    out: dict[str, float | None] = dict.fromkeys(PARAM_NAMES)
    dh = truth.get("dh") or {}
    for n in DH_NAMES:
        if n in dh:
            out[n] = float(dh[n])
    mount = truth.get("mount")
    if mount is None:
        return out, ""
    if result.method != "markers":
        return out, "Mount truth not shown: a targetless calibration has no world frame (the mount is not estimated)."
    fit = truth_frame(result, truth)
    if fit is None:
        return out, "Mount truth not shown: the simulator frame could not be aligned to the marker frame W."
    T_W_sim, how = fit
    p = Pose.from_matrix(T_W_sim @ Pose(**{k: float(mount[k]) for k in MOUNT_NAMES}).matrix())
    for n in MOUNT_NAMES:
        out[n] = getattr(p, n)
    return out, (f"Mount truth re-expressed in the marker frame W (true marker positions fitted to the tape map "
                 f"{how}).")


def _tunnel_truth(truth: dict[str, Any] | None) -> dict[str, float | None]:
    t = None if truth is None else truth.get("tunnel")
    if t is None:
        return dict.fromkeys(TUNNEL_KEYS)
    get = t.get if isinstance(t, dict) else (lambda k: getattr(t, k, None))
    return {k: _f(get(k)) for k in TUNNEL_KEYS}


def _angle_err(n: str, est: float, ref: float) -> float:
    d = est - ref
    return (d + math.pi) % (2 * math.pi) - math.pi if n in ANGLE_NAMES else d


def residual_summary(result: CalibrationResult) -> str:
    """One line, the same in the terminal and the report: residual RMS over the marker returns and markers used."""
    sol = result.solution
    if result.markers is None:
        return (f"plane residual RMS {sol.residual_rms_m * 1000:.2f} mm over {sol.n_surface_returns} returns on "
                f"{len(result.plane_fit.planes)} planes of the scene (targetless)")
    n_markers = int((_marker_counts(result) > 0).sum())
    return (f"residual RMS {sol.residual_rms_m * 1000:.2f} mm over {sol.n_observations} marker returns on "
            f"{n_markers} of {len(result.markers.marker_ids)} markers")


def _marker_lines(result: CalibrationResult) -> list[str]:
    """The report's summary lines on the markers, blobs and tape."""
    assert result.markers is not None and result.detections is not None and result.association is not None
    counts = _marker_counts(result)
    ids = result.markers.marker_ids
    lines = [
        f"- markers used: {int((counts > 0).sum())} of {len(ids)} "
        f"({', '.join(i for i, c in zip(ids, counts, strict=True) if c > 0) or 'none'})",
        f"- blobs detected: {len(result.detections.blobs)}, matched to markers: {result.association.n_matched}"
        f"{' (marker map mirrored)' if result.association.mirrored else ''}",
        f"- marker map from the tape: RMS {result.markers.rms_m * 1000:.2f} mm, stress {result.markers.stress:.2g}"
        f"{', coplanar layout' if result.markers.coplanar else ''}",
    ]
    for p in result.markers.dropped_pairs:
        lines.append(f"- tape pair {p.id_i}-{p.id_j} dropped: measured {p.measured_m:.3f} m, the other pairs put it "
                     f"at {p.predicted_m:.3f} m ({p.error_m * 1000:+.0f} mm); re-measure it")
    return lines


def _per_marker_lines(result: CalibrationResult) -> list[str]:
    assert result.markers is not None
    counts = _marker_counts(result)
    lines = ["", "## Per-marker residuals", "", "| marker | returns | RMS [mm] |", "|---|---|---|"]
    per = np.asarray(result.solution.per_marker_rms_m, dtype=float).reshape(-1)
    for i, mid in enumerate(result.markers.marker_ids):
        v = per[i] if i < per.size else float("nan")
        lines.append(f"| {mid} | {int(counts[i])} | {f'{v * 1000:.2f}' if math.isfinite(v) else '-'} |")
    return lines


def _side_by_side_lines(result: CalibrationResult, truth: dict[str, float | None] | None) -> list[str]:
    """The DH estimates of every method run on this recording, with their 1-sigma (and the truth when known)."""
    if len(result.side_by_side) < 3:
        return []
    lines = ["", "## The methods side by side (DH: estimate +- 1-sigma)", "",
             "| method | " + " | ".join(f"{n} [{_unit(n)}]" for n in DH_NAMES) + " |", "|---|---|---|---|---|"]
    for name, sol in result.side_by_side.items():
        est = sol.params.as_dict()
        lines.append(f"| {name} | " + " | ".join(f"{_disp(n, est[n])} +- {_disp(n, param_sigma(sol, n))}"
                                                 for n in DH_NAMES) + " |")
    if truth is not None:
        lines.append("| truth | " + " | ".join(_disp(n, truth.get(n)) for n in DH_NAMES) + " |")
    return lines


def _plane_lines(result: CalibrationResult) -> list[str]:
    """The scene's planes and their thickness (RMS distance of their returns from their best-fit plane) with
    the nominal and with the calibrated DH parameters."""
    fit = result.plane_fit
    lines = ["", "## The scene's planes (frame M)", "",
             "| plane | normal | offset [m] | returns | thickness before [mm] | after [mm] |",
             "|---|---|---|---|---|---|"]
    for k, (p, n, b, a) in enumerate(zip(fit.planes, fit.n_returns, fit.rms_before_m, fit.rms_after_m,
                                         strict=True)):
        lines.append(f"| {k} | ({p.normal[0]:+.3f}, {p.normal[1]:+.3f}, {p.normal[2]:+.3f}) | {p.offset_m:.3f} | "
                     f"{int(n)} | {b * 1000:.2f} | {a * 1000:.2f} |")
    from .planes import squareness_deg

    sq_b, sq_a = squareness_deg(fit.normals_before), squareness_deg(fit.normals_after)
    if sq_b.size:
        lines += ["", f"Corners (pairs of planes within 20 deg of perpendicular, {sq_b.size}): mean |90 deg - angle| "
                  f"{sq_b.mean():.3f} deg with the nominal DH, {sq_a.mean():.3f} deg calibrated (a box's walls are "
                  "square to within its build)."]
    return lines


def render_report(result: CalibrationResult, truth: dict[str, Any] | None = None) -> str:
    """The calibration report as Markdown: parameters with sigma (and the paper's baseline, the start values
    and, given ``truth`` as loaded from ground_truth.yaml, the truth and the errors), per-marker residuals,
    tunnel geometry before/after."""
    sol = result.solution
    est = sol.params.as_dict()
    start = result.start.as_dict()
    base = result.baseline.params.as_dict() if result.baseline is not None else None
    tp, truth_note = _truth_params(result, truth) if truth is not None else (None, "")
    targetless = result.markers is None
    lines = ["# Rotating LRF calibration" + (" (targetless: the scene's planes, no markers)" if targetless else ""),
             "", f"- status: {sol.status} ({sol.n_iterations} iterations)", f"- {residual_summary(result)}"]
    if targetless:
        fit = result.plane_fit
        if fit.held:
            lines.append(f"- held at the nominal value (the scene does not determine them): {', '.join(fit.held)}")
    else:
        lines += _marker_lines(result)
    if result.baseline is not None:
        lines.append(f"- baseline (paper method) residual RMS: {result.baseline.residual_rms_m * 1000:.2f} mm "
                     f"over {result.baseline.n_observations} returns")
    lines += ["", "## Parameters", ""]
    head = ["parameter", "unit", "start", "estimate", "sigma"]
    if base is not None:
        head.append("baseline (paper)")
    if tp is not None:
        head += ["truth", "error"] + (["baseline error"] if base is not None else [])
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for n in DH_NAMES if targetless else PARAM_NAMES:
        held = targetless and n in result.plane_fit.held
        row = [n, _unit(n), _disp(n, start[n]), _disp(n, est[n]) + (" (held)" if held else ""),
               _disp(n, param_sigma(sol, n))]
        if base is not None:
            row.append(_disp(n, base[n]))
        if tp is not None:
            t = tp[n]
            row += [_disp(n, t), _disp(n, None if t is None else _angle_err(n, est[n], t))]
            if base is not None:
                row.append(_disp(n, None if t is None else _angle_err(n, base[n], t)))
        lines.append("| " + " | ".join(row) + " |")
    rot = [param_sigma(sol, n) for n in ("rx", "ry", "rz")]
    if not targetless:
        lines += ["", "The mount's rotation is estimated on SO(3): its 1-sigma is that of a small rotation vector in "
                  "frame M, (rx, ry, rz) = (" + ", ".join(_disp("rx", v) for v in rot) + ") deg; roll, pitch and "
                  "yaw are the same rotation written as URDF angles (no sigma: theirs would come from the Euler "
                  "angles' singularity)."]
    else:
        lines.append("")
    if targetless:
        lines.append("Without markers there is no world frame: the mount pose is not estimated.")
    if math.isfinite(sol.clock_offset_sigma_s):
        lines.append(f"Clock offset (laser stamp - servo stamp): {sol.clock_offset_s * 1000:+.2f} ms, 1-sigma "
                     f"{sol.clock_offset_sigma_s * 1000:.2f} ms (estimated).")
    else:
        lines.append(f"Clock offset (laser stamp - servo stamp): {sol.clock_offset_s * 1000:+.2f} ms (held, not "
                     "estimated).")
    if math.isfinite(sol.range_offset_sigma_m):
        lines.append(f"Range offset (every return): {sol.range_offset_m * 1000:+.2f} +- "
                     f"{sol.range_offset_sigma_m * 1000:.2f} mm; marker-return range bias: "
                     f"{sol.marker_range_bias_m * 1000:+.2f} +- {sol.marker_range_bias_sigma_m * 1000:.2f} mm "
                     "(estimated).")
    if truth_note:
        lines += ["", truth_note]
    if result.checks:
        lines += ["", "## Checks", "", "| check | result | numbers |", "|---|---|---|"]
        lines += [f"| {c.name} | {'passed' if c.passed else '**FAILED**'} | {c.detail} |" for c in result.checks]
    if result.notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in result.notes]

    lines += _plane_lines(result) if targetless else _per_marker_lines(result)
    lines += _side_by_side_lines(result, tp)

    g0, g1 = result.geometry_before, result.geometry_after
    if g0 is not None or g1 is not None or (truth is not None and truth.get("tunnel")):
        tt = _tunnel_truth(truth)
        head = ["quantity", "before [m]", "after [m]"]
        if truth is not None:
            head += ["truth [m]", "error before [mm]", "error after [mm]"]
        lines += ["", "## Tunnel geometry (RANSAC planes in the reprojected cloud)", "",
                  "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for k, label in zip(TUNNEL_KEYS, ("width (wall to wall)", "height (floor to ceiling)",
                                          "distance to the plate"), strict=True):
            b = None if g0 is None else _f(getattr(g0, k))
            a = None if g1 is None else _f(getattr(g1, k))
            row = [label, "-" if b is None else f"{b:.4f}", "-" if a is None else f"{a:.4f}"]
            if truth is not None:
                t = tt[k]
                row.append("-" if t is None else f"{t:.4f}")
                for v in (b, a):
                    row.append("-" if v is None or t is None else f"{(v - t) * 1000:+.1f}")
            lines.append("| " + " | ".join(row) + " |")
    if result.timings_s:
        lines += ["", "## Timings", "", "| stage | s |", "|---|---|"]
        lines += [f"| {k} | {v:.3f} |" for k, v in result.timings_s.items()]
    return "\n".join(lines) + "\n"


# --- the output folder ----------------------------------------------------------------------------------------

def write_calibration(
    out_dir: str | Path,
    result: CalibrationResult,
    report_md: str | None = None,
    figures: dict[str, Path] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write calibration.yaml, rig.urdf, cloud_before.ply, cloud_after.ply, report.md and the figures.

    Everything is written into a temporary folder beside ``out_dir`` that is renamed into place when complete.
    Args:
        report_md: the report text; default :func:`render_report` (without truth).
        figures: name -> existing file; each is copied into the folder under its file name.
        overwrite: replace an existing non-empty ``out_dir`` that this project wrote (see
            :func:`check_replaceable`); otherwise InputError.
    Returns:
        out_dir.
    """
    out = check_replaceable(out_dir, overwrite)
    with atomic_folder(out, "lrfcal calibrate") as tmp:
        text = yaml.safe_dump(calibration_dict(result), sort_keys=False, default_flow_style=None, width=110)
        (tmp / "calibration.yaml").write_text(text, encoding="utf-8")
        (tmp / "rig.urdf").write_text(urdf_snippet(result.solution.params), encoding="utf-8")
        write_ply(tmp / "cloud_before.ply", result.cloud_before_M, result.cloud_intensity)
        after_i = result.cloud_intensity if len(result.cloud_intensity) == len(result.cloud_after_M) else None
        write_ply(tmp / "cloud_after.ply", result.cloud_after_M, after_i)
        report = render_report(result) if report_md is None else report_md
        (tmp / "report.md").write_text(report, encoding="utf-8")
        for name, src in (figures or {}).items():
            src = Path(src)
            if not src.is_file():
                raise InputError(f"{src}: figure {name!r} not found")
            shutil.copyfile(src, tmp / src.name)
    return out


#: The file every output folder of this project holds: which tool wrote it and the entries it wrote. Only a
#: folder with this file and no other entries may be replaced (``--overwrite``).
MANIFEST_NAME = ".lrf-calib-output.yaml"


def write_manifest(folder: Path, tool: str) -> Path:
    """Write :data:`MANIFEST_NAME` into ``folder``, listing its current top-level entries (written by ``tool``)."""
    folder = Path(folder)
    entries = sorted(p.name for p in folder.iterdir() if p.name != MANIFEST_NAME)
    text = yaml.safe_dump({"written_by": tool, "entries": entries}, sort_keys=False)
    path = folder / MANIFEST_NAME
    path.write_text(text, encoding="utf-8")
    return path


def _manifest_entries(folder: Path) -> set[str] | None:
    """The entries a manifest in ``folder`` lists, or None when there is no readable manifest."""
    try:
        data = yaml.safe_load((folder / MANIFEST_NAME).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return None
    if not isinstance(data, dict) or not isinstance(data.get("entries"), list):
        return None
    return {str(e) for e in data["entries"]}


def check_replaceable(out_dir: str | Path, overwrite: bool) -> Path:
    """Refuse an output folder that must not be written: return ``out_dir`` as a Path when it may be.

    Allowed: a missing or empty folder; with ``overwrite``, a folder that this project wrote (it holds the
    manifest :data:`MANIFEST_NAME`) and that holds nothing else than the entries the manifest lists. Anything
    else raises :class:`InputError` naming the folder and, where there are any, the files we did not write.
    """
    out = Path(out_dir)
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise InputError(f"{out}: output exists and is not a folder")
    if not out.is_dir():
        return out
    try:
        present = sorted(p.name for p in out.iterdir())
    except OSError as e:
        raise InputError(f"{out}: cannot read the output folder ({e.strerror})") from None
    if not present:
        return out
    # what --overwrite would be refused for is said already without it: one message, one fix
    listed = _manifest_entries(out)
    if listed is None:
        raise InputError(f"{out}: output folder exists, is not empty and was not written by lrf-calib (no "
                         f"{MANIFEST_NAME}), so it is never replaced, not even with --overwrite: choose another "
                         "output folder")
    foreign = [n for n in present if n != MANIFEST_NAME and n not in listed]
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise InputError(f"{out}: output folder exists and holds files lrf-calib did not write ({shown}), so it is "
                         "never replaced, not even with --overwrite: move them away or choose another output folder")
    if not overwrite:
        raise InputError(f"{out}: output folder exists (written by lrf-calib): use --overwrite to replace it")
    return out


def check_writable(out: str | Path) -> Path:
    """Refuse an output path that cannot be created, before any work: its nearest existing ancestor must be a
    folder in which a folder can be made (tried with an empty hidden folder, removed at once).

    Raises:
        InputError: naming the path and the ancestor that blocks it.
    """
    out = Path(out)
    anc = out.absolute().parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(f"{out}: cannot write the output folder here ({anc} is not a folder)")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise InputError(f"{out}: cannot write the output folder here ({anc} is not writable)")
    try:  # permissions do not tell everything (root, /proc, read-only mounts, full disks): try it, before the work
        os.rmdir(tempfile.mkdtemp(prefix=".lrf-write-probe-", dir=anc))
    except OSError as e:
        raise InputError(f"{out}: cannot write the output folder here ({anc}: {e.strerror or e})") from None
    return out


@contextmanager
def atomic_folder(out: str | Path, tool: str) -> Iterator[Path]:
    """Build an output folder atomically: yields a new temporary folder beside ``out`` to write into; when the
    block completes, the manifest (which ``tool`` wrote what) is added and the folder renamed into place
    (:func:`swap_into_place`); when it fails, the temporary folder is removed and ``out`` is left as it was."""
    out = Path(out)
    tmp = make_temp_beside(out)
    try:
        yield tmp
        write_manifest(tmp, tool)
        swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def make_temp_beside(out: Path) -> Path:
    """A new hidden temporary folder next to ``out`` (created with its parents; usual permissions).

    Raises:
        InputError: the parent folder cannot be created or written.
    """
    out = Path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
        os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700; give the folder the usual mode
    except OSError as e:
        raise InputError(f"{out}: cannot write the output folder here ({e.strerror or e})") from None
    return tmp


def _resolved(p: str | Path) -> Path:
    return Path(p).expanduser().resolve()


def check_no_overlap(outputs: dict[str, str | Path | None], inputs: dict[str, str | Path | None],
                     may_nest_in: tuple[str, ...] = ()) -> None:
    """Refuse outputs that are, contain or lie inside an input.

    Args:
        outputs, inputs: ``{label: path}``; None entries are skipped.
        may_nest_in: labels of input folders an output may lie inside (e.g. the recording folder, where
            ``REC/calibration`` touches no input file), though never be or contain.
    Raises:
        InputError: naming the output, the input and how they overlap.
    """
    for o_label, o in outputs.items():
        if o is None:
            continue
        ro = _resolved(o)
        for i_label, i in inputs.items():
            if i is None:
                continue
            ri = _resolved(i)
            if ro == ri:
                how = "is"
            elif ro in ri.parents:
                how = "contains"
            elif ri in ro.parents and i_label not in may_nest_in:
                how = "lies inside"
            else:
                continue
            raise InputError(f"{o}: {o_label} {how} the {i_label} {i}: outputs never overlap inputs (nor each "
                             "other); choose another path")


def swap_into_place(tmp: Path, out: Path) -> None:
    """Rename the finished folder tmp to out, replacing an existing out (moved aside, then deleted)."""
    if not out.exists():
        os.rename(tmp, out)
        return
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    old.rmdir()
    os.rename(out, old)
    try:
        os.rename(tmp, out)
    except BaseException:
        os.rename(old, out)
        raise
    shutil.rmtree(old, ignore_errors=True)


__all__ = [
    "MANIFEST_NAME", "align_truth_frame", "atomic_folder", "calibration_dict", "check_no_overlap", "check_replaceable",
    "check_writable", "dh_matrix", "make_temp_beside", "render_report", "residual_summary", "swap_into_place",
    "truth_dict", "truth_frame", "urdf_snippet", "write_calibration", "write_manifest",
]
