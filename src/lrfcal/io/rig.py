"""The rig file (nominal.yaml): design DH values and where a bag keeps the scans and the servo angle.

Keys are documented in docs/formats.md ("The rig file"). Parsed with pydantic models that forbid unknown keys;
every problem becomes one :class:`~lrfcal.errors.InputError` line naming the file, the key and the value.
The pre-issue-8 keys ``scan_topic``, ``joint_topic``, ``joint_name`` are still accepted (they mean
``scan: {topic}`` and ``servo: {topic, joint}``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, model_validator

from lrfcal.errors import InputError
from lrfcal.io.yamlfile import read_yaml

Stamp = Literal["header", "receive"]
ServoStamp = Literal["header", "receive", "scan"]
Unit = Literal["rad", "deg", "counts"]
Echo = Literal["first", "strongest", "last"]
Motion = Literal["continuous", "step"]
Angles = Literal["increment", "span"]
LogColumn = Literal["time", "angle", "ignore"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _radians(v: float) -> float:
    """An angle in rad; beyond 2 pi it was written in degrees (90 instead of 1.5708)."""
    if abs(v) > 2 * math.pi:
        raise ValueError(f"{v:g} rad is beyond 2 pi: it looks like degrees; angles are in radians ({v:g} deg = "
                         f"{math.radians(v):.6g} rad)")
    return v


Radians = Annotated[float, AfterValidator(_radians)]

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


class DHModel(_Strict):
    """eq. (3) DH parameters [m, rad]."""

    a: DHOffset
    alpha: Radians
    b: DHOffset
    beta: Radians


class MountModel(_Strict):
    """T_W_M: translation [m], then R = Rz(yaw) Ry(pitch) Rx(roll) [rad]."""

    x: MountMetres
    y: MountMetres
    z: MountMetres
    roll: Radians
    pitch: Radians
    yaw: Radians


class ScanSource(_Strict):
    """Where the LaserScans are: ``topic``; ``field``: dotted path of a LaserScan inside a larger message
    (None: the topic is a sensor_msgs/LaserScan); ``stamp``: header.stamp or the bag's receive time;
    ``echo``: which return of a sensor_msgs/MultiEchoLaserScan (urg_node's ``echoes``) to take per beam:
    ``first`` (nearest valid), ``last`` (farthest valid) or ``strongest`` (highest intensity; the default).
    Ignored for LaserScan topics. ``angles``: where beam i points when a scan's angle_increment and angle_max
    disagree (a driver's off-by-one): ``increment``, angle_min + i angle_increment; ``span``, angle_min + i
    (angle_max - angle_min) / (N - 1); None (the default): such a scan is refused, naming this key
    (lrfcal.io.bag_scans)."""

    topic: str = Field(default="/scan", min_length=1)
    field: str | None = None
    stamp: Stamp = "header"
    echo: Echo = "strongest"
    angles: Angles | None = None


class TfSource(_Strict):
    """The servo angle as the rotation of ``child`` relative to ``parent`` in /tf (and /tf_static) about
    ``axis`` of the parent frame (the joint axis): angle = 2 atan2(q_axis, q_w)."""

    parent: str = Field(min_length=1)
    child: str = Field(min_length=1)
    axis: Literal["x", "y", "z"] = "z"


class ServoSource(_Strict):
    """Where the motor angle lambda is, and how to turn the recorded number into radians.

    lambda = sign * value * unit_factor + offset_rad, unit_factor = 1 (rad), pi/180 (deg) or
    2 pi / counts_per_rev (counts). ``joint`` picks a name in sensor_msgs/JointState; ``field`` a numeric
    field (dotted path) of any other message (default ``data`` for std_msgs, ``current_pos`` for
    dynamixel_msgs/JointState); ``stamp: scan`` means the angle travels in the scan's own message.
    """

    topic: str | None = "/joint_states"
    field: str | None = None
    joint: str | None = None
    unit: Unit = "rad"
    counts_per_rev: float | None = Field(default=None, gt=0)
    sign: Literal[1, -1] = 1
    offset_rad: float = 0.0
    stamp: ServoStamp = "header"
    tf: TfSource | None = None
    #: how the servo moves while the laser scans: ``continuous`` (it turns during a scan: every beam's angle is
    #: interpolated at the beam's own time) or ``step`` (step and scan: it stands still while the laser scans, so
    #: every beam of a scan takes the angle at the scan's stamp). None: ``step`` when the angle travels in the
    #: scan's own message (stamp: scan), else ``continuous``.
    motion: Motion | None = None

    @model_validator(mode="after")
    def _consistent(self) -> ServoSource:
        if self.unit == "counts" and self.counts_per_rev is None:
            raise ValueError("unit counts needs counts_per_rev (e.g. 4096 for a Dynamixel MX)")
        if self.unit != "counts" and self.counts_per_rev is not None:
            raise ValueError(f"counts_per_rev is only used with unit: counts (unit is {self.unit})")
        if self.joint is not None and self.field is not None:
            raise ValueError("give either joint (sensor_msgs/JointState) or field (other messages), not both")
        if self.tf is not None and (self.field is not None or self.joint is not None or self.stamp == "scan"):
            raise ValueError("tf takes the angle from /tf: do not combine it with field, joint or stamp: scan")
        if self.stamp == "scan" and self.field is None:
            raise ValueError("stamp: scan needs field: the angle's dotted path inside the scan's message")
        return self

    def steps(self) -> bool:
        """True when the servo stands still during each scan (``motion``, its default from ``stamp``)."""
        return self.motion == "step" or (self.motion is None and self.stamp == "scan")

    def unit_factor(self) -> float:
        """Radians per recorded unit."""
        if self.unit == "deg":
            return math.pi / 180.0
        if self.unit == "counts":
            assert self.counts_per_rev is not None
            return 2.0 * math.pi / self.counts_per_rev
        return 1.0

    def describe(self) -> str:
        """One line naming the source, e.g. ``/joint_states[servo]`` or ``/tf base->tilt``."""
        if self.tf is not None:
            return f"/tf {self.tf.parent}->{self.tf.child} (about {self.tf.axis})"
        what = f"[{self.joint}]" if self.joint else (f".{self.field}" if self.field else "")
        topic = "(the scan's message)" if self.stamp == "scan" else self.topic
        return f"{topic}{what} ({self.unit}, sign {self.sign:+d}, offset {self.offset_rad:g} rad, " \
               f"stamp {self.stamp}, {'step and scan' if self.steps() else 'continuous motion'})"


class LogLayout(_Strict):
    """How a scan log (a text file, one row per scan; docs/formats.md "Scan logs") is laid out: the leading
    ``columns`` before the ranges (``time`` and ``angle`` once each, ``ignore`` for anything else, e.g. a row
    number), their units, an optional header row of beam angles, and the scanner's layout where the log has no
    header. The motor angle's unit, sign, offset and motion are the rig file's ``servo`` keys, as for a bag."""

    columns: tuple[LogColumn, ...] = ("time", "angle")
    time_unit: Literal["s", "ms", "us", "ns"] = "s"
    range_unit: Literal["m", "mm"] = "m"
    #: ``none``: every row is a scan; ``angles``: the first row holds, after the leading columns, every beam's
    #: angle (in ``beam_angle_unit``), which then replaces angle_min_rad / angle_increment_rad
    header: Literal["none", "angles"] = "none"
    beam_angle_unit: Literal["rad", "deg"] = "rad"
    intensities: bool = False
    angle_min_rad: Radians | None = None
    angle_increment_rad: Annotated[float, Field(gt=-0.5, lt=0.5)] | None = None
    #: time between beams [s]; absent: scan period / beams-per-revolution (as the bag reader assumes for 0)
    time_increment_s: Annotated[float, Field(gt=0.0, lt=1.0)] | None = None
    range_min_m: Annotated[float, Field(ge=0.0, lt=10.0)] = 0.0
    range_max_m: Annotated[float, Field(gt=0.0, le=1000.0)] | None = None

    @model_validator(mode="after")
    def _consistent(self) -> LogLayout:
        for need in ("time", "angle"):
            if self.columns.count(need) != 1:
                raise ValueError(f"columns must name {need} exactly once (got {list(self.columns)}); e.g. "
                                 f"[ignore, time, angle] for a row number, a time and the motor angle")
        if self.header == "angles" and (self.angle_min_rad is not None or self.angle_increment_rad is not None):
            raise ValueError("header: angles takes the beam angles from the header row: leave out angle_min_rad "
                             "and angle_increment_rad")
        if self.header == "none" and (self.angle_min_rad is None or self.angle_increment_rad is None):
            raise ValueError("a log without header row needs angle_min_rad and angle_increment_rad (the scanner's "
                             "first beam and step, from its datasheet or driver), or header: angles")
        if self.angle_increment_rad == 0.0:
            raise ValueError("angle_increment_rad must not be 0")
        if self.range_max_m is not None and self.range_max_m <= self.range_min_m:
            raise ValueError(f"range_max_m {self.range_max_m:g} must exceed range_min_m {self.range_min_m:g}")
        return self

    def time_units_per_s(self) -> float:
        """Units of the time column per second (a divisor: 5100 ms / 1000 is exactly the float 5.1)."""
        return {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9}[self.time_unit]

    def range_units_per_m(self) -> float:
        """Units of a range per metre (a divisor)."""
        return 1e3 if self.range_unit == "mm" else 1.0


class RigFile(_Strict):
    """nominal.yaml: ``dh`` (required), ``mount``, ``marker_radius_m``, ``beam_divergence_rad``,
    ``range_sigma_m``, ``scan``, ``servo``, ``log`` (a scan log's layout; and the old keys ``scan_topic``,
    ``joint_topic``, ``joint_name``)."""

    dh: DHModel
    mount: MountModel | None = None
    marker_radius_m: Annotated[float, AfterValidator(_positive_radius),
                               _metres(MAX_MARKER_RADIUS_M, "a marker radius")] = 0.005
    #: the scanner's full beam divergence [rad]: its footprint on a marker (lrfcal.model.sphere.footprint_depth); 0 (the
    #: default) models the beam as its axis, right for a footprint much smaller than the markers
    beam_divergence_rad: float = Field(default=0.0, ge=0.0, lt=0.1)
    #: the scanner's range noise, 1-sigma [m]: the calibration's default --range-sigma (absent: 0.010, the
    #: UTM-30LX-EW's specified repeatability); lrfsim writes its sensor's noise here
    range_sigma_m: float | None = Field(default=None, gt=0.0, le=1.0)
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


def is_placeholder_dh(dh: Any) -> bool:
    """Whether DH values (a mapping or an object with a, alpha, b, beta) are all 0: the placeholder a rig file from
    ``lrfcal inspect`` holds when the recording did not determine a proposal."""
    get = dh.get if isinstance(dh, dict) else (lambda n, default=None: getattr(dh, n, default))
    return all(get(n, None) == 0.0 for n in ("a", "alpha", "b", "beta"))


def refuse_placeholder_dh(dh: Any, where: str, before: str) -> None:
    """The one check of calibrate and reproject: a rig file whose DH are the placeholder is refused.

    Raises:
        InputError: ``dh`` is the placeholder (the line names ``where``, the key ``dh`` and what to do ``before``).
    """
    if is_placeholder_dh(dh):
        raise InputError(f"{where}: dh: a, alpha, b and beta are all 0, the placeholder `lrfcal inspect` writes: fill "
                         f"in the design values (m, rad; docs/formats.md) before {before}")


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


__all__ = ["DHModel", "LogLayout", "MountModel", "RigFile", "ScanSource", "ServoSource", "TfSource", "load_rig",
           "parse_rig", "validation_message", "with_overrides"]
