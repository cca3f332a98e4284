"""Compare a calibration with the simulator's ground truth: the paper's Table I and Table III.

The calibration's world frame W is the MDS frame of the tape measurements, not the simulator's world. The mount
pose is therefore compared after aligning W: the rigid transform that maps the true marker positions onto the
MDS marker coordinates (see :func:`truth_alignment`) carries the estimated T_W_M into the simulator's frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrfcal import CalibrationResult, MarkerEvidence, PlaneEvidence, Solution, TunnelGeometry
from lrfcal.errors import CalibrationError, InputError
from lrfcal.io.truth import truth_dict, truth_frame
from lrfcal.io.yamlfile import read_yaml
from lrfcal.model.kinematics import DH, DH_NAMES, Params, Pose, dh_from_mapping, pose_from_mapping, wrap_angle
from lrfsim.scenario.sections import Tolerances


@dataclass(frozen=True)
class Truth:
    """ground_truth.yaml: true DH, mount T_W_M, marker centres (n, 3) in the simulator's W, tunnel dims."""

    dh: DH
    mount: Pose
    markers: dict[str, np.ndarray]
    marker_radius_m: float | None  # None: a marker-less scene
    clock_offset_s: float
    tunnel: dict[str, float] | None


def load_truth(path: str | Path) -> Truth:
    """Read ground_truth.yaml (docs/formats.md)."""
    path = Path(path)
    data = read_yaml(path, "ground truth")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping")
    try:
        markers = {str(k): np.asarray(v, dtype=float).reshape(3) for k, v in (data["markers"] or {}).items()}
        return Truth(
            dh=dh_from_mapping(data["dh"], f"{path}: dh"),
            mount=pose_from_mapping(data["mount"], f"{path}: mount"),
            markers=markers,
            marker_radius_m=None if data["marker_radius_m"] is None else float(data["marker_radius_m"]),
            clock_offset_s=float(data.get("clock_offset_s", 0.0)),
            tunnel=data.get("tunnel"),
        )
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"{path}: malformed ground truth ({e})") from None


@dataclass(frozen=True)
class ParamRow:
    name: str
    unit: str
    truth: float
    ours: float
    paper: float | None
    tolerance: float

    @property
    def error(self) -> float:
        return _diff(self.name, self.ours, self.truth)

    @property
    def paper_error(self) -> float | None:
        return None if self.paper is None else _diff(self.name, self.paper, self.truth)

    @property
    def ok(self) -> bool:
        return abs(self.error) <= self.tolerance


@dataclass(frozen=True)
class TunnelRow:
    name: str
    truth: float
    calibrated: float | None
    nominal: float | None
    tolerance: float

    @property
    def ok(self) -> bool:
        return self.calibrated is not None and abs(self.calibrated - self.truth) <= self.tolerance


@dataclass(frozen=True)
class Comparison:
    """Table I (DH and mount pose) and Table III (tunnel dimensions) against the truth, with pass/fail."""

    dh_rows: tuple[ParamRow, ...]
    mount_position_error_m: float
    mount_rotation_error_rad: float
    paper_mount_position_error_m: float | None
    paper_mount_rotation_error_rad: float | None
    tunnel_rows: tuple[TunnelRow, ...]
    tolerances: Tolerances

    @property
    def failures(self) -> list[str]:
        out = [f"{r.name}: |error| {abs(r.error):.3g} > {r.tolerance:.3g}" for r in self.dh_rows if not r.ok]
        if self.mount_position_error_m > self.tolerances.position_m:  # NaN (targetless: no mount) never fails
            out.append(
                f"mount position: error {self.mount_position_error_m:.3g} m > {self.tolerances.position_m}"
            )
        if self.mount_rotation_error_rad > self.tolerances.rotation_rad:
            out.append(
                f"mount rotation: error {self.mount_rotation_error_rad:.3g} rad > {self.tolerances.rotation_rad:.3g}"
            )
        out += [f"tunnel {r.name}: {r.calibrated} vs truth {r.truth}" for r in self.tunnel_rows if not r.ok]
        return out

    @property
    def ok(self) -> bool:
        return not self.failures


def truth_alignment(result: CalibrationResult, truth: Truth) -> np.ndarray:
    """T_W_sim (4, 4): maps the simulator's world into the calibration's marker frame W.

    From the marker correspondence the calibration used (lrfcal.io.truth.truth_frame): a mirror-symmetric layout
    may legitimately come out of MDS mirrored with its ids swapped across the symmetry, and only the returns tell
    which physical marker each map marker is.
    """
    found = truth_frame(result, truth_dict(truth))
    if found is None:
        raise CalibrationError("the marker map does not fit the true marker positions within 1 cm RMS")
    return found[0]


def mount_in_truth_frame(result: CalibrationResult, params: Params, truth: Truth) -> np.ndarray:
    """The estimated T_W_M carried into the simulator's world frame: T_sim_W @ T_W_M, shape (4, 4)."""
    return np.linalg.inv(truth_alignment(result, truth)) @ params.mount.matrix()


def _mount_errors(result: CalibrationResult, solution: Solution, truth: Truth) -> tuple[float, float]:
    T_est = mount_in_truth_frame(result, solution.params, truth)
    T_true = truth.mount.matrix()
    position = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    R = T_true[:3, :3].T @ T_est[:3, :3]
    rotation = float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))
    return position, rotation


def compare(result: CalibrationResult, truth: Truth, tolerances: Tolerances) -> Comparison:
    """Build Tables I and III for a calibration result against the ground truth."""
    tol = {
        "a": tolerances.a_m,
        "b": tolerances.b_m,
        "alpha": tolerances.alpha_rad,
        "beta": tolerances.beta_rad,
    }
    match result.evidence:
        case MarkerEvidence() as marks:  # the paper's method beside ours, on the same returns (when it ran)
            paper = marks.baseline
            pos, rot = _mount_errors(result, result.solution, truth)
        case PlaneEvidence():  # no world frame and no mount estimated: its mount errors are NaN
            paper, (pos, rot) = None, (math.nan, math.nan)
    rows = tuple(
        ParamRow(
            name=n,
            unit="m" if n in ("a", "b") else "rad",
            truth=getattr(truth.dh, n),
            ours=getattr(result.solution.params.dh, n),
            paper=None if paper is None else getattr(paper.params.dh, n),
            tolerance=tol[n],
        )
        for n in DH_NAMES
    )
    ppos, prot = (None, None) if paper is None else _mount_errors(result, paper, truth)
    tunnel_rows: tuple[TunnelRow, ...] = ()
    if truth.tunnel:
        tunnel_rows = tuple(
            TunnelRow(
                name=n.removesuffix("_m"),
                truth=float(truth.tunnel[n]),
                calibrated=_dim(result.geometry_after, n),
                nominal=_dim(result.geometry_before, n),
                tolerance=tolerances.tunnel_m,
            )
            for n in ("width_m", "height_m", "plate_distance_m")
        )
    return Comparison(rows, pos, rot, ppos, prot, tunnel_rows, tolerances)


def _dim(geometry: TunnelGeometry | None, name: str) -> float | None:
    return None if geometry is None else getattr(geometry, name)


def _diff(name: str, value: float, truth: float) -> float:
    if name in ("alpha", "beta", "roll", "pitch", "yaw"):
        return float(wrap_angle(value - truth))
    return float(value - truth)
