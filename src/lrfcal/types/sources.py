"""Where a recording keeps its scans and its servo angle, and how a scan log is laid out: the rig file's
``scan:``, ``servo:`` and ``log:`` sections (docs/formats.md, "The rig file"), which :class:`lrfcal.types.Nominal`
carries to the readers (lrfcal.io.bag, lrfcal.io.scanlog). Validated pydantic models that forbid unknown keys;
lrfcal.io.rig reads the rest of the rig file and turns a validation error into one line.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

Stamp = Literal["header", "receive"]
ServoStamp = Literal["header", "receive", "scan"]
Unit = Literal["rad", "deg", "counts"]
Echo = Literal["first", "strongest", "last"]
Motion = Literal["continuous", "step"]
Angles = Literal["increment", "span"]
LogColumn = Literal["time", "angle", "ignore"]


class Strict(BaseModel):
    """A section of the rig file: unknown keys, changes after validation and NaN or inf refused."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _radians(v: float) -> float:
    """An angle in rad; beyond 2 pi it was written in degrees (90 instead of 1.5708)."""
    if abs(v) > 2 * math.pi:
        raise ValueError(f"{v:g} rad is beyond 2 pi: it looks like degrees; angles are in radians ({v:g} deg = "
                         f"{math.radians(v):.6g} rad)")
    return v


Radians = Annotated[float, AfterValidator(_radians)]


class ScanSource(Strict):
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



class TfSource(Strict):
    """The servo angle as the rotation of ``child`` relative to ``parent`` in /tf (and /tf_static) about
    ``axis`` of the parent frame (the joint axis): angle = 2 atan2(q_axis, q_w)."""

    parent: str = Field(min_length=1)
    child: str = Field(min_length=1)
    axis: Literal["x", "y", "z"] = "z"



class ServoSource(Strict):
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



class LogLayout(Strict):
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



__all__ = ["Angles", "Echo", "LogColumn", "LogLayout", "Motion", "Radians", "ScanSource", "ServoSource",
           "ServoStamp", "Stamp", "Strict", "TfSource", "Unit"]
