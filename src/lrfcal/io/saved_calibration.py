"""A calibration as `lrfcal calibrate` saved it (calibration.yaml, docs/formats.md), read back whole: every
parameter's value, which were estimated and their covariance with the cross terms, the rig file the recording was
read with and the scanner it saw, and the options it ran with (`lrfcal check` starts a new calibration from them and
compares the two).

A calibration written before `covariance_estimated`, `rig` and `scanner` were (format_version 1 all along: they are
added keys) is read too: its covariance is the 10 x 10 of the mount and the DH with the clock offset and the
intrinsics uncorrelated with them (:attr:`SavedCalibration.notes` says so), and the recording is read with its own rig
file.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io.rig import RigFile, parse_rig
from lrfcal.io.yamlfile import read_yaml
from lrfcal.model.kinematics import DH, DH_NAMES, ESTIMATE_NAMES, MOUNT_NAMES, Pose
from lrfcal.model.unknowns import INTRINSICS

FloatArray = NDArray[np.float64]

#: the file a calibration folder holds
CALIBRATION_FILE = "calibration.yaml"


@dataclass(frozen=True)
class SavedCalibration:
    """A calibration.yaml read back. ``values``: every parameter's value by name (the DH, the clock offset, the
    intrinsics, estimated or held; the mount's x, y, z when there is one), SI units; ``names`` and ``covariance``
    (k, k): the estimated parameters and their covariance (the mount's rotation as rx, ry, rz, a rotation vector in
    frame M); ``held``: the parameters it did not estimate, with why; ``mount``: the mount pose (None: targetless);
    ``rig``: the rig file it read its recording with (None in older files); ``scanner``: frame_id, beams,
    angle_min_rad, angle_increment_rad (None in older files); ``config``: its options as written."""

    path: Path
    method: str
    values: dict[str, float]
    names: tuple[str, ...]
    covariance: FloatArray
    held: dict[str, str]
    mount: Pose | None
    rig: RigFile | None
    scanner: dict[str, Any] | None
    config: dict[str, Any]
    notes: tuple[str, ...] = field(default=())
    #: the names of the checks it failed and was written anyway (--force): its values and sigmas are not trusted
    failed_checks: tuple[str, ...] = field(default=())

    @property
    def dh(self) -> DH:
        return DH(*(self.values[n] for n in DH_NAMES))

    def covariance_of(self, names: list[str]) -> FloatArray:
        """The covariance (len(names), len(names)) of ``names`` (each estimated)."""
        i = [self.names.index(n) for n in names]
        return self.covariance[np.ix_(i, i)]


def calibration_file(path: str | Path) -> Path:
    """The calibration.yaml of ``path``: a calibration folder (it must hold one) or the file itself.

    Raises:
        InputError: a folder without calibration.yaml, or nothing at ``path``.
    """
    path = Path(path)
    if path.is_dir():
        if not (path / CALIBRATION_FILE).is_file():
            raise InputError(f"{path}: no {CALIBRATION_FILE} in this folder: give the folder `lrfcal calibrate -o` "
                             f"wrote, or its {CALIBRATION_FILE}")
        return path / CALIBRATION_FILE
    if not path.exists():
        raise InputError(f"{path}: calibration not found (a calibration folder or its {CALIBRATION_FILE})")
    return path


def _number(data: Any, where: str) -> float | None:
    """A plain number (None for null); anything else refused naming ``where``."""
    if data is None:
        return None
    if isinstance(data, bool) or not isinstance(data, int | float):
        raise InputError(f"{where}: expected a number, got {data!r}")
    return float(data)


def _value_sigma(data: Any, where: str) -> tuple[float, float | None]:
    """``{value, sigma}`` -> (value, sigma or None)."""
    if not isinstance(data, dict) or "value" not in data:
        raise InputError(f"{where}: expected {{value: ..., sigma: ...}}, got {data!r}")
    value = _number(data["value"], f"{where}.value")
    if value is None:
        raise InputError(f"{where}.value: missing (null)")
    return value, _number(data.get("sigma"), f"{where}.sigma")


def read_saved(path: str | Path) -> SavedCalibration:
    """Read a calibration folder or its calibration.yaml (module docstring).

    Raises:
        InputError: no such file, not YAML, or not a calibration (naming the key that is missing or wrong and what
            to give instead).
    """
    file = calibration_file(path)
    data = read_yaml(file, "calibration file")
    if not isinstance(data, dict) or "dh" not in data or "method" not in data:
        raise InputError(f"{file}: not a calibration (no 'method' and 'dh' keys): give the calibration.yaml "
                         "`lrfcal calibrate` wrote, or its folder")
    method = data["method"]
    if method not in ("markers", "targetless"):
        raise InputError(f"{file}: method: expected markers or targetless, got {method!r}")
    values: dict[str, float] = {}
    sigma: dict[str, float | None] = {}
    dh = data["dh"]
    if not isinstance(dh, dict):
        raise InputError(f"{file}: dh: expected a mapping of a, alpha, b, beta, got {dh!r}")
    for n in DH_NAMES:
        values[n], sigma[n] = _value_sigma(dh.get(n), f"{file}: dh.{n}")
    mount = None
    if data.get("mount") is not None:
        m = data["mount"]
        if not isinstance(m, dict):
            raise InputError(f"{file}: mount: expected a mapping, got {m!r}")
        pose = {n: _value_sigma(m.get(n), f"{file}: mount.{n}") for n in MOUNT_NAMES}
        mount = Pose(**{n: v for n, (v, _) in pose.items()})
        for n in ("x", "y", "z"):
            values[n], sigma[n] = pose[n]
        rot = data.get("mount_rotation_sigma_rad") or {}
        for n in ("rx", "ry", "rz"):
            values[n], sigma[n] = 0.0, _number(rot.get(n), f"{file}: mount_rotation_sigma_rad.{n}")
    if data.get("clock_offset_s") is not None:
        values["clock_offset"], sigma["clock_offset"] = _value_sigma(data["clock_offset_s"], f"{file}: clock_offset_s")
    intr = data.get("intrinsics") or {}
    if not isinstance(intr, dict):
        raise InputError(f"{file}: intrinsics: expected a mapping, got {intr!r}")
    held: dict[str, str] = {}
    for n in INTRINSICS:
        if n in intr:
            values[n], sigma[n] = _value_sigma(intr[n], f"{file}: intrinsics.{n}")
            if sigma[n] is None:
                held[n] = str(intr[n].get("held") or "held")
    for n in (*DH_NAMES, "clock_offset"):
        if n in values and sigma.get(n) is None:
            held[n] = ("held at the nominal value (the scene's planes do not determine it)"
                       if n in (data.get("held_at_nominal") or ()) else "held")
    names, cov, notes = _covariance(data, sigma, file)
    rig = parse_rig(data["rig"], f"{file}: rig") if data.get("rig") is not None else None
    scanner = data.get("scanner") if isinstance(data.get("scanner"), dict) else None
    config: dict[str, Any] = data["config"] if isinstance(data.get("config"), dict) else {}
    failed = tuple(str(c.get("name")) for c in data.get("checks") or () if isinstance(c, dict) and
                   c.get("passed") is False)
    return SavedCalibration(file, method, values, names, cov, held, mount, rig, scanner, config, notes, failed)


def _covariance(data: dict[str, Any], sigma: dict[str, float | None], file: Path
                ) -> tuple[tuple[str, ...], FloatArray, tuple[str, ...]]:
    """The estimated parameters and their covariance: ``covariance_estimated`` when written, else the 10 x 10
    ``covariance`` for the mount and the DH and the sigmas of the others (uncorrelated: a note says so)."""
    written = data.get("covariance_estimated")
    if isinstance(written, dict) and isinstance(written.get("names"), list):
        names = tuple(str(n) for n in written["names"])
        try:
            cov = np.array(written["matrix"], dtype=float).reshape(len(names), len(names))
        except (TypeError, ValueError):
            raise InputError(f"{file}: covariance_estimated.matrix: expected a {len(names)} x {len(names)} matrix of "
                             "numbers") from None
        if not np.all(np.isfinite(cov)) or np.any(np.diag(cov) <= 0):
            raise InputError(f"{file}: covariance_estimated.matrix: not finite and positive on its diagonal")
        return names, 0.5 * (cov + cov.T), ()
    names_l = [n for n in (*ESTIMATE_NAMES, "clock_offset", *INTRINSICS) if (s := sigma.get(n)) is not None
               and math.isfinite(s) and s > 0]
    cov = np.diag(np.array([sigma[n] or 0.0 for n in names_l], dtype=float) ** 2)
    ten = data.get("covariance") or {}
    matrix = ten.get("matrix") if isinstance(ten, dict) else None
    if matrix is not None:
        try:
            M = np.array([[math.nan if v is None else v for v in row] for row in matrix], dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{file}: covariance.matrix: expected a 10 x 10 matrix of numbers") from None
        idx = [i for i, n in enumerate(names_l) if n in ESTIMATE_NAMES]
        for i in idx:
            for j in idx:
                v = M[ESTIMATE_NAMES.index(names_l[i]), ESTIMATE_NAMES.index(names_l[j])]
                if math.isfinite(v):
                    cov[i, j] = v
    return tuple(names_l), cov, ("the calibration holds no covariance_estimated (written before it was): the clock "
                                 "offset and the intrinsics are taken as uncorrelated with the DH",)


__all__ = ["CALIBRATION_FILE", "SavedCalibration", "calibration_file", "read_saved"]
