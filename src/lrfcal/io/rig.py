"""The rig file (nominal.yaml): design DH values and where a bag keeps the scans and the servo angle.

Its sections ``scan:``, ``servo:`` and ``log:`` are :mod:`lrfcal.types.sources`' models (ScanSource, ServoSource,
TfSource, LogLayout: the recording's :class:`~lrfcal.types.Nominal` carries them; named here too, as the rig file's
parts). Keys are documented in docs/formats.md ("The rig file"). Parsed with pydantic models that forbid unknown keys;
every problem becomes one :class:`~lrfcal.errors.InputError` line naming the file, the key and the value.
The pre-issue-8 keys ``scan_topic``, ``joint_topic``, ``joint_name`` are still accepted (they mean
``scan: {topic}`` and ``servo: {topic, joint}``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any

import yaml
from pydantic import AfterValidator, Field, ValidationError, model_validator

from lrfcal.errors import InputError
from lrfcal.io.yamlfile import read_yaml
from lrfcal.types.sources import LogLayout, Radians, ScanSource, ServoSource, Strict, TfSource

#: Beyond these a length was written in millimetres (a: 10 for 10 mm): a scan plane's offsets from the motor axis
#: (DH a, b) are centimetres on any rig; a marker is a few millimetres to a few centimetres; the mount lies in
#: the frame of the markers, which the laser sees, so within its longest range (60 m, Hokuyo UTM-30LX) [m].
MAX_DH_OFFSET_M = 2.0
MAX_MARKER_RADIUS_M = 0.5
MAX_MOUNT_M = 60.0


def _metres(limit_m: float, what: str) -> AfterValidator:
    """A length in m; beyond ``limit_m`` it was written in millimetres (or centimetres)."""

    def check(v: float) -> float:
        if abs(v) > limit_m:
            raise ValueError(f"{v:g} m is beyond {limit_m:g} m for {what}: it looks like millimetres; lengths are in "
                             f"metres ({v:g} mm = {v / 1000:.6g} m)")
        return v

    return AfterValidator(check)


def _positive_radius(v: float) -> float:
    """A marker sphere's radius: positive (0 or less is no sphere; the markers are fitted as spheres)."""
    if v <= 0.0:
        raise ValueError(f"{v:g} m is no sphere: the markers' radius in metres must be > 0 (e.g. 0.005 for balls 10 "
                         "mm across; leave the key out for that default)")
    return v


DHOffset = Annotated[float, _metres(MAX_DH_OFFSET_M, "a DH offset")]
MountMetres = Annotated[float, _metres(MAX_MOUNT_M, "the mount (the laser sees its markers)")]


class DHModel(Strict):
    """eq. (3) DH parameters [m, rad]."""

    a: DHOffset
    alpha: Radians
    b: DHOffset
    beta: Radians


#: beyond these a DH tolerance was written in millimetres or degrees (a 1-sigma of half a metre or of 90 deg is no
#: design value) [m, rad]
MAX_DH_TOLERANCE_M, MAX_DH_TOLERANCE_RAD = 0.5, math.pi / 2


def _tolerance_angle(v: float) -> float:
    """A DH angle's 1-sigma in rad; beyond 90 deg it was written in degrees."""
    if v > MAX_DH_TOLERANCE_RAD:
        raise ValueError(f"{v:g} rad is beyond {MAX_DH_TOLERANCE_RAD:.4g} rad (90 deg) for a DH tolerance: it looks "
                         f"like degrees; angles are in radians ({v:g} deg = {math.radians(v):.6g} rad)")
    return v


DHTolerance = Annotated[float, Field(gt=0.0), _metres(MAX_DH_TOLERANCE_M, "a DH tolerance")]
AngleTolerance = Annotated[float, Field(gt=0.0), AfterValidator(_tolerance_angle)]


class DHToleranceModel(Strict):
    """The design DH values' 1-sigma [m, rad]: how well the drawing knows them. A drawing's +-t with the truth
    anywhere within is t / sqrt(3) (a rectangular distribution, JCGM 100:2008 "GUM" 4.3.7)."""

    a: DHTolerance
    alpha: AngleTolerance
    b: DHTolerance
    beta: AngleTolerance


class MountModel(Strict):
    """T_W_M: translation [m], then R = Rz(yaw) Ry(pitch) Rx(roll) [rad]."""

    x: MountMetres
    y: MountMetres
    z: MountMetres
    roll: Radians
    pitch: Radians
    yaw: Radians


class SelfBoxModel(Strict):
    """One of the rig's own parts the scanner sees, a box fixed to the motor frame M: its centre's pose in M and its
    edge lengths along its own x, y, z [m]."""

    pose: MountModel
    size_m: tuple[Annotated[float, Field(gt=0.0, le=10.0)], Annotated[float, Field(gt=0.0, le=10.0)],
                  Annotated[float, Field(gt=0.0, le=10.0)]]


class RigFile(Strict):
    """nominal.yaml: ``dh`` (required), ``dh_tolerance``, ``mount``, ``marker_radius_m``, ``beam_divergence_rad``,
    ``range_sigma_m``, ``range_pattern``, ``self_boxes``, ``scan``, ``servo``, ``log`` (a scan log's layout; and the
    old keys ``scan_topic``, ``joint_topic``, ``joint_name``)."""

    dh: DHModel
    #: the design DH values' 1-sigma (absent: 10 mm and 5 deg, lrfcal.config.DEFAULT_NOMINAL_TOLERANCE): the
    #: targetless cost's prior, the held parameters' uncertainty, the mirror-image check's scale
    dh_tolerance: DHToleranceModel | None = None
    mount: MountModel | None = None
    marker_radius_m: Annotated[float, AfterValidator(_positive_radius),
                               _metres(MAX_MARKER_RADIUS_M, "a marker radius")] = 0.005
    #: the scanner's full beam divergence [rad]: its footprint on a marker (lrfcal.model.sphere.footprint_depth); 0 (the
    #: default) models the beam as its axis, right for a footprint much smaller than the markers
    beam_divergence_rad: float = Field(default=0.0, ge=0.0, lt=0.1)
    #: the scanner's range noise, 1-sigma [m]: the calibration's default --range-sigma (absent: 0.010, the
    #: UTM-30LX-EW's specified repeatability); lrfsim writes its sensor's noise here
    range_sigma_m: float | None = Field(default=None, gt=0.0, le=1.0)
    #: the scanner's ranges carry an error along the scan, the same in every scan (the URG-04LX's, docs/real-data.md):
    #: a targetless calibration estimates it with the DH (lrfcal.model.range_pattern; ``--range-pattern``)
    range_pattern: bool = False
    #: the rig's own parts the scanner sees (its stand, at large tilts), boxes fixed to M: a targetless calibration
    #: leaves the returns of the beams that meet them out of the scene (lrfcal.stages.targetless.own_returns)
    self_boxes: tuple[SelfBoxModel, ...] = ()
    scan: ScanSource | None = None
    servo: ServoSource | None = None
    #: how a scan log is laid out (lrfcal.io.scanlog); ignored for bags
    log: LogLayout | None = None
    scan_topic: str | None = Field(default=None, min_length=1)
    joint_topic: str | None = Field(default=None, min_length=1)
    joint_name: str | None = Field(default=None, min_length=1)

    @model_validator(mode="after")
    def _no_double(self) -> RigFile:
        if self.scan is not None and self.scan_topic is not None:
            raise ValueError("scan_topic and scan: both given; keep scan: {topic: ...} only")
        if self.servo is not None and (self.joint_topic is not None or self.joint_name is not None):
            raise ValueError("joint_topic/joint_name and servo: both given; keep servo: {topic, joint} only")
        return self

    def scan_source(self) -> ScanSource:
        """The scan source, the old ``scan_topic`` key folded in."""
        if self.scan is not None:
            return self.scan
        return ScanSource(topic=self.scan_topic or "/scan")

    def servo_source(self) -> ServoSource:
        """The servo source, the old ``joint_topic``/``joint_name`` keys folded in (default
        /joint_states, joint ``servo``)."""
        if self.servo is not None:
            return self.servo
        return ServoSource(topic=self.joint_topic or "/joint_states", joint=self.joint_name or "servo")


def validation_message(err: ValidationError, where: str) -> str:
    """The first pydantic error (an unknown key first) as one line: ``where: key.path: message, got value``."""
    errs = err.errors()
    e = next((x for x in errs if x.get("type") == "extra_forbidden"), errs[0])  # a typo explains the rest
    loc = ".".join(str(p) for p in e.get("loc", ()))
    msg = e.get("msg", "invalid").removeprefix("Value error, ")
    if e.get("type") == "extra_forbidden":
        msg = "unknown key"
    elif e.get("type") == "missing":
        msg = "missing"
    got = e.get("input")
    tail = "" if e.get("type") in ("extra_forbidden", "missing") or isinstance(got, dict) else f", got {got!r}"
    return f"{where}: {loc + ': ' if loc else ''}{msg}{tail}"


def parse_rig(data: Any, where: str) -> RigFile:
    """Validate a mapping (the loaded YAML) as a :class:`RigFile`; ``where`` prefixes error messages."""
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected a mapping with keys dh, mount, marker_radius_m, scan, servo, "
                         f"got {data!r}")
    try:
        return RigFile.model_validate(data)
    except ValidationError as err:
        raise InputError(validation_message(err, where)) from None


def load_rig(path: str | Path) -> RigFile:
    """Read and validate a rig file (nominal.yaml)."""
    path = Path(path)
    data = read_yaml(path, "nominal file")
    return parse_rig(data, str(path))


def with_overrides(
    scan: ScanSource | None, servo: ServoSource | None, *, scan_topic: str | None = None, scan_field: str | None = None,
    scan_stamp: str | None = None, servo_topic: str | None = None, servo_field: str | None = None,
    joint: str | None = None, unit: str | None = None, counts_per_rev: float | None = None,
    sign: int | None = None, servo_offset: float | None = None, servo_stamp: str | None = None,
    tf_parent: str | None = None, tf_child: str | None = None, tf_axis: str | None = None,
) -> tuple[ScanSource | None, ServoSource | None]:
    """The rig file's scan / servo sources (ScanSource / ServoSource, or None) with the CLI's
    one-off options applied; bad values raise InputError naming the option."""
    sd = scan.model_dump() if isinstance(scan, ScanSource) else {}
    vd = servo.model_dump() if isinstance(servo, ServoSource) else {}
    sd.update({k: v or None for k, v in (("topic", scan_topic), ("field", scan_field), ("stamp", scan_stamp))
               if v is not None})  # an empty string clears a key (e.g. --scan-field "")
    upd: dict[str, str | float | int | None]
    upd = {k: v for k, v in (("topic", servo_topic), ("field", servo_field), ("joint", joint), ("unit", unit),
                             ("counts_per_rev", counts_per_rev), ("sign", sign), ("offset_rad", servo_offset),
                             ("stamp", servo_stamp)) if v is not None}
    upd = {k: (None if v == "" else v) for k, v in upd.items()}
    if "field" in upd:
        vd.pop("joint", None)
    if "joint" in upd:
        vd.pop("field", None)
    if upd.get("unit", "counts") != "counts":
        vd.pop("counts_per_rev", None)
    vd.update(upd)
    if tf_parent or tf_child:
        vd.update(tf={"parent": tf_parent, "child": tf_child, "axis": tf_axis or "z"}, topic=None, field=None,
                  joint=None)
    try:
        s = ScanSource.model_validate(sd) if (sd or isinstance(scan, ScanSource)) else None
        v = ServoSource.model_validate(vd) if (vd or isinstance(servo, ServoSource)) else None
    except ValidationError as err:
        raise InputError(validation_message(err, "options").replace("options: ", "option ", 1)) from None
    return s, v


def rig_snippet(scan: ScanSource | None, servo: ServoSource | None, dh: dict[str, float] | None = None, *,
                multiecho: bool = False, comment: str | None = None) -> str:
    """The rig file's YAML (dh, scan, servo) that reads a bag, as ``lrfcal inspect`` proposes it; dh placeholders
    when not known. ``multiecho``: the scan topic is a MultiEchoLaserScan, whose ``echo`` choice is then written out
    even when it is the default (for a LaserScan topic it is meaningless and left out). ``comment``: the line above
    ``dh`` (a proposal's uncertainty, or why there is none; default: fill in the placeholders)."""
    data: dict[str, Any] = {"dh": dict(dh) if dh else {"a": 0.0, "alpha": 0.0, "b": 0.0, "beta": 0.0}}
    if scan is not None:
        data["scan"] = scan.model_dump(exclude_none=True)
        if not multiecho and scan.echo == "strongest":  # the default, and meaningless for LaserScan topics
            data["scan"].pop("echo")
    if servo is not None:
        s = servo.model_dump(exclude_none=True)
        if servo.tf is not None:
            s.pop("topic", None)
        data["servo"] = s
    text = yaml.safe_dump(data, sort_keys=False, default_flow_style=False)
    if comment is not None:
        text = comment.rstrip() + "\n" + text
    elif not dh:
        text = "# dh: fill in from the drawings (m, rad; docs/formats.md)\n" + text
    return text

__all__ = ["DHModel", "LogLayout", "MountModel", "RigFile", "ScanSource", "ServoSource", "TfSource", "load_rig",
           "parse_rig", "rig_snippet", "validation_message", "with_overrides"]
