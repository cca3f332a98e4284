"""calibration.yaml: the content of a calibration's result file as plain Python values (docs/formats.md).

Frames: W is the marker frame (from the tape distances), M the motor frame; the mount is T_W_M. NaN and infinite
values are written as null.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import DH_NAMES, ESTIMATE_NAMES, MOUNT_NAMES
from lrfcal.model.noise import shown
from lrfcal.model.unknowns import BY_NAME
from lrfcal.result import CalibrationResult, MarkerEvidence, PlaneEvidence
from lrfcal.types import MarkerMap, Nominal, Scans, Solution, TunnelGeometry

FloatArray = NDArray[np.float64]

FORMAT_VERSION = 1


def plain_float(v: Any) -> float | None:
    """A plain float for YAML, None for NaN/inf/None."""
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


_f = plain_float  # the short name the dicts below use


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
        "covariance_estimated": _estimated_dict(sol),
        "clock_offset_s": {"value": _f(sol.clock_offset_s), "sigma": _f(sol.clock_offset_sigma_s)},
        "range_offset_m": {"value": _f(sol.range_offset_m), "sigma": _f(sol.range_offset_sigma_m)},
        "marker_range_bias_m": {"value": _f(sol.marker_range_bias_m), "sigma": _f(sol.marker_range_bias_sigma_m)},
        "intrinsics": _intrinsics_dict(sol),
        "residual_rms_m": _f(sol.residual_rms_m),
        "n_observations": int(sol.n_observations),
        "reduced_chi2": _f(sol.reduced_chi2),
        # the range noise's correlation between neighbouring beams the marker returns show (a scenario's
        # sensor.noise_correlation for `lrfsim plan`), and whether the covariance holds it (lrfcal.model.noise.shown)
        "range_noise_correlation": {"rho": _f(sol.range_correlation[0]), "pairs": int(sol.range_correlation[1]),
                                    "in_covariance": shown(*sol.range_correlation)},
        "status": str(sol.status),
    }


def _estimated_dict(sol: Solution) -> dict[str, Any]:
    """The covariance of every unknown the solution estimated, with the cross terms between the mount, the DH, the
    clock offset and the intrinsics (Solution.estimated_covariance; what `lrfcal check` compares a new calibration
    with)."""
    names, cov = sol.estimated_covariance()
    return {"names": list(names), "matrix": [[_f(v) for v in row] for row in cov]}


def _rig_dict(nominal: Nominal) -> dict[str, Any]:
    """The rig file the calibration read the recording with (lrfcal.io.rig.RigFile's keys: the nominal values and
    where the bag keeps the scans and the servo angle, one-off command-line settings applied), so that the
    calibration alone reads a new recording of the same rig (`lrfcal check`)."""
    out: dict[str, Any] = {"dh": {n: float(v) for n, v in zip(DH_NAMES, nominal.dh.vector(), strict=True)}}
    if nominal.dh_tolerance is not None:
        out["dh_tolerance"] = {n: float(v) for n, v in zip(DH_NAMES, nominal.dh_tolerance, strict=True)}
    if nominal.mount is not None:
        out["mount"] = {n: float(getattr(nominal.mount, n)) for n in MOUNT_NAMES}
    out["marker_radius_m"] = float(nominal.marker_radius_m)
    out["beam_divergence_rad"] = float(nominal.beam_divergence_rad)
    if nominal.range_sigma_m is not None:
        out["range_sigma_m"] = float(nominal.range_sigma_m)
    if nominal.range_pattern:
        out["range_pattern"] = True
    if nominal.self_boxes:
        out["self_boxes"] = [{"pose": {n: float(getattr(b.pose, n)) for n in MOUNT_NAMES},
                              "size_m": [float(v) for v in b.size_m]} for b in nominal.self_boxes]
    for key, section in (("scan", nominal.scan), ("servo", nominal.servo), ("log", nominal.log)):
        if section is not None:
            out[key] = section.model_dump(mode="json", exclude_none=True)
    return out


def scanner_dict(scans: Scans) -> dict[str, Any]:
    """The scanner as its scans describe it: frame_id, the most beams a scan carried, the median angle_min and
    angle_increment [rad] (what tells one scanner from another: `lrfcal check` refuses a calibration of another)."""
    mu = np.asarray(scans.mu_rad, dtype=float)
    inc = float(np.median(mu[:, 1] - mu[:, 0])) if mu.ndim == 2 and mu.shape[1] > 1 else math.nan
    return {"frame_id": scans.frame_id, "beams": int(np.max(scans.beam_counts)) if scans.beam_counts.size else 0,
            "angle_min_rad": _f(float(np.median(mu[:, 0])) if mu.size else math.nan), "angle_increment_rad": _f(inc)}


def _intrinsics_dict(sol: Solution) -> dict[str, Any]:
    """Every intrinsic of the rig model (lrfcal.model.unknowns): value, 1-sigma (null when held), unit, and whether
    it was estimated or held (and, when held by default, why)."""
    out: dict[str, Any] = {}
    for name, (value, sigma) in sol.intrinsics.items():
        u = BY_NAME[name]
        estimated = math.isfinite(sigma)
        out[name] = {"value": _f(value), "sigma": _f(sigma), "unit": u.unit,
                     "estimated": estimated, "held": None if estimated else (u.held or "held by this calibration")}
    return out


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


def _plain(v: Any) -> Any:
    """Plain YAML values of a configuration: tuples as lists, NaN and inf as null."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, tuple | list):
        return [_plain(x) for x in v]
    if isinstance(v, float):
        return _f(v)
    return v


# --- calibration.yaml -----------------------------------------------------------------------------------------

def calibration_dict(result: CalibrationResult) -> dict[str, Any]:
    """The content of calibration.yaml (plain Python types; NaN -> None): the solution, then the keys of the
    result's evidence (markers or the scene's planes), then what every result has."""
    sol = result.solution
    out: dict[str, Any] = {
        "format_version": FORMAT_VERSION,
        "method": result.method,
        "units": "m, rad; frames: W marker frame (tape distances), M motor frame; T_W_M = mount",
        **_solution_dict(sol),
        "n_iterations": int(sol.n_iterations),
    }
    baseline = None
    match result.evidence:
        case MarkerEvidence() as ev:
            out.update(_marker_dict(sol, ev))
            baseline = ev.baseline
        case PlaneEvidence() as ev:
            out.update(_targetless_dict(ev))
    out.update({
        "checks": [{"name": c.name, "passed": bool(c.passed), "detail": c.detail} for c in result.checks],
        "notes": list(result.notes),
        "servo_sign": int(result.servo_sign),
        "rig": _rig_dict(result.recording.nominal),
        "scanner": scanner_dict(result.recording.scans),
        "start": {k: float(v) for k, v in result.start.as_dict().items()},
        "baseline": None if baseline is None else {
            "method": "seed paper: blob peaks only, one motor angle per scan",
            **_solution_dict(baseline),
        },
        "tunnel": {"before": _geometry_dict(result.geometry_before), "after": _geometry_dict(result.geometry_after)},
        "timings_s": {str(k): _f(v) for k, v in result.timings_s.items()},
        "config": None if result.config is None else _plain(result.config.model_dump()),
    })
    return out


def _targetless_dict(evidence: PlaneEvidence) -> dict[str, Any]:
    """A targetless calibration's own keys: no world frame (mount null), the parameters held at nominal, and the
    scene's planes with their thickness before and after."""
    fit = evidence.plane_fit
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


def map_sigma(solution: Solution, markers: MarkerMap) -> dict[str, float | None]:
    """Per DH parameter, the 1-sigma the marker map's own uncertainty contributes to ``solution`` (None when not
    computed)."""
    G, C = solution.map_sensitivity, markers.covariance
    if G is None or C is None:
        return {n: None for n in DH_NAMES}
    var = np.einsum("ij,jk,ik->i", G, C, G)
    return {n: _f(float(np.sqrt(max(var[ESTIMATE_NAMES.index(n)], 0.0)))) for n in DH_NAMES}


def _marker_dict(sol: Solution, evidence: MarkerEvidence) -> dict[str, Any]:
    """A marker calibration's own keys: markers used, the marker map, the association, the marker surfaces."""
    markers, detections, association = evidence.markers, evidence.detections, evidence.association
    ids = markers.marker_ids
    counts = evidence.marker_counts()
    per = np.asarray(sol.per_marker_rms_m, dtype=float).reshape(-1)
    on_surfaces = evidence.surface_returns
    return {
        "markers": {
            "used": [ids[i] for i in range(len(ids)) if counts[i] > 0],
            "unused": [ids[i] for i in range(len(ids)) if counts[i] == 0],
            "n_returns": {ids[i]: int(counts[i]) for i in range(len(ids))},
            "residual_rms_m": {ids[i]: _f(per[i]) if i < per.size else None for i in range(len(ids))},
        },
        "marker_map": {
            "stress": _f(markers.stress),
            "rms_m": _f(markers.rms_m),
            "planarity": _f(markers.planarity),
            "coplanar": bool(markers.coplanar),
            # the tape's noise as the map's redundant pairs show it, and the part of each DH sigma it makes
            # (the map's covariance carried through the solution; included in the covariance above)
            "tape_sigma_m": _f(markers.tape_sigma_m),
            "dh_sigma_from_map": map_sigma(sol, markers),
            "dropped_pairs": [  # tape pairs inconsistent with the others (gross errors), left out
                {"pair": [p.id_i, p.id_j], "measured_m": _f(p.measured_m), "predicted_m": _f(p.predicted_m),
                 "z": _f(p.z)}
                for p in markers.dropped_pairs
            ],
        },
        "association": {
            "n_blobs": len(detections.blobs),
            "n_matched": int(association.n_matched),
            "mirrored": bool(association.mirrored),
            "rms_m": _f(association.rms_m),
        },
        "surfaces": [  # the planes the markers sit on, solved jointly (stage 6b)
            {
                "markers": [ids[int(i)] for i in srf.marker_idx],
                "normal": [float(v) for v in srf.normal],
                "offset_m": float(srf.offset_m),
                "n_returns": int(np.sum(on_surfaces.surface == k)) if on_surfaces else 0,
            }
            for k, srf in enumerate(evidence.surfaces)
        ],
        "detection_threshold": _f(detections.threshold),
    }


__all__ = ["FORMAT_VERSION", "calibration_dict", "map_sigma", "param_sigma", "plain_float", "scanner_dict"]
