"""Scenario files: one pydantic model per section, ``extra="forbid"``, bounds on every number.

A scenario fully determines a simulated recording (with its seed). Units are SI; angles in rad unless the
field name says ``_deg``. Frames: W is the simulator world, z up, floor at z = 0 (for a tunnel: x along the
tunnel towards the plate, y to the left, walls at y = +-width/2; a room is placed in W by its floor centre and yaw).
"""

from __future__ import annotations

import copy
import difflib
import math
import os
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

import yaml
from pydantic import AliasChoices, BaseModel, ConfigDict, Field, ValidationError, model_validator

from lrfcal.errors import InputError
from lrfcal.io.yamlfile import read_yaml
from lrfcal.model.kinematics import DH, Pose

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]


def _d(text: str, **kw: object) -> object:
    """A pydantic Field with a description (units in brackets) and optional bounds."""
    return Field(description=text, **kw)  # type: ignore[arg-type]


class _Section(BaseModel):
    # allow_inf_nan=False: every float of every section must be finite (NaN / inf name their field)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class DHConfig(_Section):
    """DH parameters from the motor axis to the scan plane: T = Tx(a) Rx(alpha) Tz(b) Rz(beta)."""

    a: Annotated[float, _d("offset along the common normal [m]", ge=-0.5, le=0.5)]
    alpha: Annotated[float, _d("twist about the common normal [rad] (not degrees)", ge=-math.pi, le=math.pi)]
    b: Annotated[float, _d("offset along the new z axis [m]", ge=-0.5, le=0.5)]
    beta: Annotated[float, _d("rotation about the new z axis [rad] (not degrees)", ge=-math.pi, le=math.pi)]

    def to_dh(self) -> DH:
        return DH(self.a, self.alpha, self.b, self.beta)


class PoseConfig(_Section):
    """A pose: translation x, y, z [m], then R = Rz(yaw) Ry(pitch) Rx(roll) [rad] (as URDF)."""

    x: Annotated[float, _d("translation x [m]", ge=-100, le=100)] = 0.0
    y: Annotated[float, _d("translation y [m]", ge=-100, le=100)] = 0.0
    z: Annotated[float, _d("translation z [m]", ge=-100, le=100)] = 0.0
    roll: Annotated[float, _d("rotation about x, applied first [rad]", ge=-math.pi, le=math.pi)] = 0.0
    pitch: Annotated[float, _d("rotation about y [rad]", ge=-math.pi, le=math.pi)] = 0.0
    yaw: Annotated[float, _d("rotation about z, applied last [rad]", ge=-math.pi, le=math.pi)] = 0.0

    def to_pose(self) -> Pose:
        return Pose(self.x, self.y, self.z, self.roll, self.pitch, self.yaw)


class RigConfig(_Section):
    """The rig: true DH and mount pose (ground truth) and the design-drawing (nominal) values."""

    dh: Annotated[DHConfig, _d("true DH parameters (ground truth)")]
    mount: Annotated[PoseConfig, _d("true mount pose T_W_M of the motor frame M in W (ground truth)")]
    nominal_dh: Annotated[DHConfig, _d("design DH values written to nominal.yaml (the calibration's start)")]
    nominal_mount: Annotated[PoseConfig, _d("design mount pose written to nominal.yaml")]


class NoiseBand(_Section):
    """Range noise below ``up_to_m``: Gaussian with ``sigma_m`` (Hokuyo spec: repeatability sigma)."""

    up_to_m: Annotated[float, _d("upper range of this band [m]", gt=0, le=1000)]
    sigma_m: Annotated[float, _d("range noise 1-sigma in this band (a scanner's is millimetres to centimetres) [m]",
                                  ge=0, le=1)]


class IntensityConfig(_Section):
    """Intensity model (see lrfsim.lidar): counts = gain * rho * g(theta) * (r_ref / r)^2, saturated."""

    gain_counts: Annotated[float, _d("counts of a rho = 1 Lambertian target at ref_range_m, normal incidence "
                                     "[counts]", gt=0)] = 4000.0
    ref_range_m: Annotated[float, _d("reference range of gain_counts [m]", gt=0, le=1000)] = 1.0
    saturation_counts: Annotated[float, _d("largest intensity reported [counts]", gt=0, le=1e9)] = 65535.0
    relative_noise: Annotated[float, _d("multiplicative intensity noise, 1-sigma [1]", ge=0, le=1)] = 0.05
    min_detectable_counts: Annotated[float, _d("weaker returns are dropped (no return) [counts]", ge=0, le=1e9)] = 20.0


#: Published characterisations the systematic-error defaults refer to (docs/sensor_errors.md).
_REFS = ("Kneip et al. ICRA 2009 (URG-04LX); Okubo et al. 2009 (URG-04LX); Ye & Borenstein ICRA 2002 "
         "(LMS 200); Pomerleau et al. CARPI 2012 (UTM-30LX)")


class SystematicConfig(_Section):
    """Systematic range errors of the scanner (lrfsim.lidar, docs/sensor_errors.md), all off by default: the
    papers that characterise them (Kneip et al. 2009, Okubo et al. 2009, Pomerleau et al. 2012, Ye & Borenstein
    2002) show each effect, but no figure for the UTM-30LX-EW could be read for this model, so every value
    here is assumed. Added to each return before noise and quantisation:
    b = range_offset_m + intensity_bias_m_per_decade * log10(min(I, saturation) / intensity_ref_counts)
    + incidence_bias_m * theta / (1 rad) + drift_amplitude_m * exp(-(drift_elapsed_s + t) / drift_time_constant_s),
    I the return's noise-free intensity, theta the incidence angle of each footprint sub-ray, t the beam's
    time from the start of the sweep."""

    range_offset_m: Annotated[float, _d("constant added to every range (the spec's +-30 mm accuracy bounds it; "
                                        "0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    intensity_bias_m_per_decade: Annotated[float, _d(
        "range bias per decade of received intensity (range walk: bright retroreflectors read short when < 0; "
        "observed by " + _REFS + "; 0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    intensity_ref_counts: Annotated[float, _d("intensity at which the intensity bias is zero [counts]", gt=0, le=1e9)
                                    ] = 1000.0
    incidence_bias_m: Annotated[float, _d(
        "range bias per radian of incidence angle (the bias at 1 rad; b = incidence_bias_m * theta / 1 rad), per "
        "footprint sub-ray (observed by " + _REFS + "; 0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    drift_amplitude_m: Annotated[float, _d(
        "warm-up drift at power-on, decaying exponentially (time drift observed by Kneip et al. 2009 and Ye & "
        "Borenstein 2002; 0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    drift_time_constant_s: Annotated[float, _d("time constant of the warm-up drift (assumed) [s]", gt=0, le=1e6)
                                     ] = 1200.0
    drift_elapsed_s: Annotated[float, _d("time from power-on to the start of the sweep [s]", ge=0, le=1e6)] = 0.0


class EchoesConfig(_Section):
    """Multi-echo returns (the UTM-30LX-EW reports up to 3 echoes per beam; urg_node with publish_multiecho
    publishes them as sensor_msgs/MultiEchoLaserScan on ``echoes``). Footprint sub-rays are grouped by range:
    sorted by range, a gap wider than ``separation_m`` starts a new echo; each echo is the power-weighted mean
    of its group (lrfsim.lidar). Off by default (no echoes topic written)."""

    enabled: Annotated[bool, _d("write the echoes topic beside /scan")] = False
    topic: Annotated[str, _d("topic of the MultiEchoLaserScan messages", min_length=1)] = "/echoes"
    separation_m: Annotated[float, _d("sub-ray ranges further apart than this are separate echoes (value "
                                      "assumed) [m]", gt=0, le=100)] = 0.1
    max_echoes: Annotated[int, _d("echoes kept per beam, nearest first (UTM-30LX-EW: 3) [1]", ge=1, le=8)] = 3


class SensorConfig(_Section):
    """The scanner; defaults: the Hokuyo UTM-30LX-EW (spec sheet: 270 deg in 0.25 deg steps, 25 ms per scan,
    0.023-60 m, repeatability 10 mm below 10 m and 30 mm below 30 m; LaserScan fields as urg_node fills them)."""

    n_beams: Annotated[int, _d("beams per scan [1]", ge=2, le=100000)] = 1081
    angle_min_rad: Annotated[float, _d("bearing of beam 0 (LaserScan angle_min) [rad]", ge=-math.pi,
                                       le=math.pi)] = -2.356194490192345
    angle_increment_rad: Annotated[float, _d("bearing step between beams [rad]", gt=0, le=math.pi)] = 2 * math.pi / 1440
    scan_period_s: Annotated[float, _d("time from one scan to the next (LaserScan scan_time) [s]", gt=0, le=10)] = 0.025
    time_increment_s: Annotated[float, _d("time between beams (LaserScan time_increment) [s]", gt=0, le=1)
                                ] = 0.025 / 1440
    range_min_m: Annotated[float, _d("shortest range reported [m]", gt=0, le=1000)] = 0.023
    range_max_m: Annotated[float, _d("longest range reported [m]", gt=0, le=1000)] = 60.0
    no_return: Annotated[Literal["nan", "inf"], _d("value written for a beam without return")] = "nan"
    noise: Annotated[bool, _d("add range and intensity noise")] = True
    noise_bands: Annotated[tuple[NoiseBand, ...], _d("range noise by range band, in increasing up_to_m")] = (
        NoiseBand(up_to_m=10.0, sigma_m=0.010),
        NoiseBand(up_to_m=30.0, sigma_m=0.030),
        NoiseBand(up_to_m=60.0, sigma_m=0.050),
    )
    noise_correlation: Annotated[float, _d(
        "correlation of the range noise of neighbouring beams in a scan: an AR(1) process along the beams, rho^k "
        "at k beams apart (0: independent; measured 0.70 on a real URG-04LX, docs/real-data.md; no public figure "
        "for the UTM-30LX-EW, so 0 by default) [1]", ge=0, lt=1)] = 0.0
    quantisation_m: Annotated[float, _d("range resolution (0: none) [m]", ge=0, le=1)] = 0.001
    divergence_rad: Annotated[float, _d("full beam divergence angle; unverified for the UTM-30LX, see README "
                                        "[rad]", ge=0, lt=0.1)] = 0.0044
    footprint_rays: Annotated[int, _d("rays per beam footprint (1: centre ray only) [1]", ge=1, le=64)] = 7
    intensity: Annotated[IntensityConfig, _d("intensity model")] = IntensityConfig()
    systematic: Annotated[SystematicConfig, _d("systematic range errors (all off by default; "
                                               "docs/sensor_errors.md)")] = SystematicConfig()
    echoes: Annotated[EchoesConfig, _d("multi-echo returns on a MultiEchoLaserScan topic (off by default)")] = (
        EchoesConfig())

    @model_validator(mode="after")
    def _check(self) -> SensorConfig:
        if self.range_min_m >= self.range_max_m:
            raise ValueError(f"range_min_m {self.range_min_m} must be below range_max_m {self.range_max_m}")
        span_rad = (self.n_beams - 1) * self.angle_increment_rad
        if span_rad > 2 * math.pi + 1e-9:
            raise ValueError(f"the scan spans (n_beams - 1) x angle_increment_rad = {span_rad:.4g} rad, more than a "
                             "turn: check angle_increment_rad (radians per beam)")
        sweep_s = (self.n_beams - 1) * self.time_increment_s
        if sweep_s > self.scan_period_s * (1 + 1e-9):
            raise ValueError(f"the beams take (n_beams - 1) x time_increment_s = {sweep_s:.4g} s, longer than "
                             f"scan_period_s {self.scan_period_s:g} s: check time_increment_s (seconds per beam)")
        if self.intensity.min_detectable_counts >= self.intensity.saturation_counts:
            raise ValueError(f"intensity.min_detectable_counts {self.intensity.min_detectable_counts:g} must be below "
                             f"intensity.saturation_counts {self.intensity.saturation_counts:g}")
        return self


class ServoConfig(_Section):
    """The servo sweep: from ``start_rad`` to ``end_rad`` at ``speed_rad_s``, ``passes`` times (alternating)."""

    joint: Annotated[str, _d("joint name in the JointState messages (as the rig file's servo.joint; the old key "
                             "joint_name is still read)", min_length=1,
                             validation_alias=AliasChoices("joint", "joint_name"))] = "servo"
    start_rad: Annotated[float, _d("motor angle where the sweep starts [rad]", ge=-2 * math.pi, le=2 * math.pi)
                         ] = math.pi / 2
    end_rad: Annotated[float, _d("motor angle where the first pass ends [rad]", ge=-2 * math.pi, le=2 * math.pi)
                       ] = -math.pi / 2
    speed_rad_s: Annotated[float, _d("cruise speed [rad/s]", gt=0, le=10)] = math.radians(10.0)
    accel_rad_s2: Annotated[float, _d("acceleration of the trapezoidal ramps [rad/s^2]", gt=0, le=1000)] = 2.0
    passes: Annotated[int, _d("number of passes, alternating direction [1]", ge=1, le=100)] = 1
    settle_s: Annotated[float, _d("standing still at each end [s]", ge=0, le=3600)] = 0.2
    rate_hz: Annotated[float, _d("JointState publishing rate [Hz]", gt=0, le=10000)] = 100.0
    encoder_counts: Annotated[int, _d("encoder counts per revolution (0: no quantisation) [1]", ge=0, le=2**30)] = 4096
    backlash_rad: Annotated[float, _d("gear play, total width (play operator) [rad]", ge=0, le=math.pi / 4)] = 0.0
    clock_offset_s: Annotated[float, _d("laser stamp minus servo stamp of the same instant [s]", ge=-1, le=1)
                              ] = 0.0

    @model_validator(mode="after")
    def _check(self) -> ServoConfig:
        if self.start_rad == self.end_rad:
            raise ValueError(f"start_rad and end_rad are equal ({self.start_rad}): nothing to sweep")
        return self


class TapeConfig(_Section):
    """The person with the tape: Gaussian noise on each measured pair; optionally only some pairs."""

    sigma_m: Annotated[float, _d("tape noise 1-sigma per measured distance [m]", ge=0, le=1)] = 0.001
    pair_fraction: Annotated[float, _d("fraction of marker pairs measured (seeded choice) [1]", gt=0, le=1)] = 1.0


class MaterialsConfig(_Section):
    """Lidar reflectivity per surface class (Lambertian albedo; retroreflector as an effective gain)."""

    painted_steel: Annotated[float, _d("albedo of the tunnel's painted steel [1]", ge=0, le=1)] = 0.35
    retroreflector: Annotated[float, _d("effective gain of the markers' retroreflective tape [1]", ge=0,
                                        le=10000)] = 200.0
    board: Annotated[float, _d("albedo of the board [1]", ge=0, le=1)] = 0.6


class ManholeConfig(_Section):
    """A rectangular opening in the plate, centred at (y, z) in W."""

    width_m: Annotated[float, _d("opening width along y [m]", gt=0, le=100)] = 0.40
    height_m: Annotated[float, _d("opening height along z [m]", gt=0, le=100)] = 0.60
    center_y_m: Annotated[float, _d("centre y in W [m]")] = 0.0
    center_z_m: Annotated[float, _d("centre z in W [m]")] = 1.15


class TunnelConfig(_Section):
    """A box-girder tunnel: floor z = 0, ceiling z = height, walls y = +-width/2, plate at x = plate_x_m."""

    width_m: Annotated[float, _d("wall to wall [m]", gt=0, le=100)] = 0.78
    height_m: Annotated[float, _d("floor to ceiling [m]", gt=0, le=100)] = 2.30
    x_min_m: Annotated[float, _d("open end of the tunnel behind the rig, x in W [m]")] = -1.0
    plate_x_m: Annotated[float, _d("the end plate, x in W [m]")] = 2.24
    wall_thickness_m: Annotated[float, _d("thickness of walls, floor, ceiling and plate [m]", gt=0, le=10)] = 0.01
    manhole: Annotated[ManholeConfig | None, _d("an opening in the plate (none by default)")] = None

    @model_validator(mode="after")
    def _check(self) -> TunnelConfig:
        if self.x_min_m >= self.plate_x_m:
            raise ValueError(f"x_min_m {self.x_min_m} must be behind plate_x_m {self.plate_x_m}")
        return self


class BoardConfig(_Section):
    """A planar board (thin box) with its centre and orientation; its front face is its local +z."""

    pose: Annotated[PoseConfig, _d("pose of the board's centre in W")]
    width_m: Annotated[float, _d("size along the board's local x [m]", gt=0, le=100)] = 1.5
    height_m: Annotated[float, _d("size along the board's local y [m]", gt=0, le=100)] = 1.0
    thickness_m: Annotated[float, _d("size along the board's local z [m]", gt=0, le=10)] = 0.01


class MeshConfig(_Section):
    """Extra geometry from an STL/OBJ file (loaded with trimesh), placed at ``pose`` in W."""

    file: Annotated[Path, _d("STL or OBJ file, relative to the scenario file's folder")]
    pose: Annotated[PoseConfig, _d("pose of the mesh in W")] = PoseConfig()
    scale: Annotated[float, _d("scale applied to the mesh's coordinates (e.g. 0.001 for mm) [1]", gt=0, le=1e6)] = 1.0
    reflectivity: Annotated[float, _d("albedo (or gain) of the mesh [1]", ge=0, le=10000)] = 0.35


class BoxConfig(_Section):
    """A solid box: its centre and orientation ``pose`` in W and its edge lengths along its own x, y, z axes."""

    pose: Annotated[PoseConfig, _d("pose of the box's centre in W")]
    size_x_m: Annotated[float, _d("edge length along the box's local x [m]", gt=0, le=100)]
    size_y_m: Annotated[float, _d("edge length along the box's local y [m]", gt=0, le=100)]
    size_z_m: Annotated[float, _d("edge length along the box's local z [m]", gt=0, le=100)]
    reflectivity: Annotated[float, _d("Lambertian albedo of its faces [1]", ge=0, le=1)] = 0.5


class RoomConfig(_Section):
    """A closed rectangular room (or, without ceiling, an open box) built from boxes: inner floor at z = 0, inner
    size size_x_m x size_y_m x size_z_m centred on (center_x_m, center_y_m) and turned by ``yaw`` about z;
    walls, floor and ceiling ``wall_thickness_m`` thick, outside the inner size."""

    size_x_m: Annotated[float, _d("inner size along the room's x (x_W at yaw 0) [m]", gt=0, le=100)]
    size_y_m: Annotated[float, _d("inner size along the room's y [m]", gt=0, le=100)]
    size_z_m: Annotated[float, _d("inner height, floor to ceiling [m]", gt=0, le=100)]
    center_x_m: Annotated[float, _d("x in W of the floor's centre [m]", ge=-100, le=100)] = 0.0
    center_y_m: Annotated[float, _d("y in W of the floor's centre [m]", ge=-100, le=100)] = 0.0
    yaw: Annotated[float, _d("rotation of the room about z_W [rad]", ge=-math.pi, le=math.pi)] = 0.0
    wall_thickness_m: Annotated[float, _d("thickness of walls, floor and ceiling [m]", gt=0, le=10)] = 0.05
    ceiling: Annotated[bool, _d("close the room with a ceiling (false: an open box)")] = True
    reflectivity: Annotated[float, _d("Lambertian albedo of walls, floor and ceiling [1]", ge=0, le=1)] = 0.5


class SceneConfig(_Section):
    """What the laser sees: a tunnel, a room, a board, boxes, extra meshes, the materials."""

    tunnel: Annotated[TunnelConfig | None, _d("a box-girder tunnel (none by default)")] = None
    room: Annotated[RoomConfig | None, _d("a rectangular room (none by default)")] = None
    board: Annotated[BoardConfig | None, _d("a planar marker board (none by default)")] = None
    boxes: Annotated[tuple[BoxConfig, ...], _d("solid boxes, e.g. furniture in a room")] = ()
    meshes: Annotated[tuple[MeshConfig, ...], _d("extra geometry")] = ()
    materials: Annotated[MaterialsConfig, _d("reflectivities")] = MaterialsConfig()


class VLayout(_Section):
    """Markers in a V on the tunnel walls: per wall, two arms meeting at the apex (lowest point)."""

    kind: Annotated[Literal["v"], _d("layout selector")] = "v"
    walls: Annotated[tuple[Literal["left", "right"], ...], _d("walls with a V")] = ("left", "right")
    x_start_m: Annotated[float, _d("x in W where the V starts [m]")] = 0.3
    x_end_m: Annotated[float, _d("x in W where the V ends [m]")] = 1.9
    z_apex_m: Annotated[float, _d("height of the apex [m]")] = 0.5
    z_top_m: Annotated[float, _d("height of the arms' ends [m]")] = 1.9
    per_arm: Annotated[int, _d("markers per arm, apex included [1]", ge=1, le=50)] = 4


class BoardLayout(_Section):
    """Markers in a grid on the board's front face (requires scene.board)."""

    kind: Annotated[Literal["board"], _d("layout selector")] = "board"
    rows: Annotated[int, _d("grid rows [1]", ge=1, le=50)] = 4
    cols: Annotated[int, _d("grid columns [1]", ge=1, le=50)] = 5
    spacing_m: Annotated[float, _d("grid spacing [m]", gt=0, le=10)] = 0.2
    jitter_m: Annotated[float, _d("random in-plane offsets (seeded), so the grid is not perfectly regular [m]",
                                  ge=0, le=1)] = 0.0


class PointsLayout(_Section):
    """Markers at explicit sphere-centre positions in W."""

    kind: Annotated[Literal["points"], _d("layout selector")] = "points"
    positions: Annotated[tuple[tuple[float, float, float], ...], _d("sphere centres [x, y, z] in W [m]")]


class MarkersConfig(_Section):
    """The retroreflective sphere markers: size and layout."""

    radius_m: Annotated[float, _d("sphere radius [m]", gt=0, le=0.2)] = 0.005
    layout: Annotated[VLayout | BoardLayout | PointsLayout,
                      _d("where the markers are: kind v, board or points", discriminator="kind")]


class Tolerances(_Section):
    """What `lrfsim run` requires of the recovery (absolute errors)."""

    a_m: Annotated[float, _d("error of a [m]", gt=0)] = 0.0005
    b_m: Annotated[float, _d("error of b [m]", gt=0)] = 0.0005
    alpha_rad: Annotated[float, _d("error of alpha [rad]", gt=0)] = math.radians(0.02)
    beta_rad: Annotated[float, _d("error of beta [rad]", gt=0)] = math.radians(0.02)
    position_m: Annotated[float, _d("error of the mount position [m]", gt=0)] = 0.005
    rotation_rad: Annotated[float, _d("error of the mount rotation (angle) [rad]", gt=0)] = math.radians(0.2)
    tunnel_m: Annotated[float, _d("error of the tunnel dimensions from the calibrated cloud [m]", gt=0)] = 0.003


class TapeOutlier(_Section):
    """A misread tape: ``error_m`` added to one measured pair, named by its two marker ids ([id_i, id_j], either
    order) or by its row index in distances.csv."""

    pair: Annotated[tuple[str, str] | Annotated[int, Field(ge=0)],
                    _d("the pair: its two marker ids [id_i, id_j] or its row in distances.csv [1]")]
    error_m: Annotated[float, _d("added to the measured distance [m]", ge=-10, le=10)]


class FaultsConfig(_Section):
    """Faults injected into the recording (lrfsim.faults), all off by default. Applied to the simulated arrays
    before writing, seeded from ``seed`` with a stream of their own, and listed in ground_truth.yaml under
    ``faults``. The laser-servo clock offset is ``servo.clock_offset_s`` (laser stamp - servo stamp), which the
    recording does not declare to the calibration."""

    tape_outliers: Annotated[tuple[TapeOutlier, ...], _d("misread tape distances (distances.csv)")] = ()
    inverted_servo: Annotated[bool, _d("joint positions and velocities negated: a servo mounted the other way "
                                       "round; the truth is unchanged")] = False
    false_blobs: Annotated[int, _d("bright spots (retroreflector-like intensity) on non-marker surfaces, each "
                                   "1-3 scans x 2-4 beams [1]", ge=0, le=200)] = 0
    occluded_markers: Annotated[int, _d("markers whose returns are removed (range and intensity those of the "
                                        "surface around, as if covered) [1]", ge=0, le=1000)] = 0
    dropped_scans_fraction: Annotated[float, _d("fraction of the scans left out of the bag (random scans) [1]",
                                                ge=0, le=0.9)] = 0.0
    encoder_spikes: Annotated[int, _d("joint-state samples whose position jumps by +-encoder_spike_rad (random "
                                      "sign) [1]", ge=0, le=100000)] = 0
    encoder_spike_rad: Annotated[float, _d("size of an encoder spike [rad]", gt=0, le=math.pi)] = 0.5
    range_noise_scale: Annotated[float, _d("every range noise band's sigma times this, applied before "
                                           "simulating [1]", ge=0, le=100)] = 1.0
    stamp_latency_s: Annotated[float, _d("scan stamps taken at receive time: each stamp this much later than its "
                                         "first beam [s]", ge=0, le=1)] = 0.0
    stamp_jitter_s: Annotated[float, _d("and a further uniform random delay in [0, this) per scan [s]", ge=0,
                                        le=1)] = 0.0


class Scenario(_Section):
    """A scenario file: everything a simulated recording depends on (units SI, angles in rad)."""

    name: Annotated[str, _d("name of the run (runs/<name>/)")]
    seed: Annotated[int, _d("random seed of every noise stream [1]", ge=0)] = 0
    rig: Annotated[RigConfig, _d("true and nominal rig geometry")]
    sensor: Annotated[SensorConfig, _d("the laser scanner")] = SensorConfig()
    servo: Annotated[ServoConfig, _d("the servo sweep and joint states")] = ServoConfig()
    scene: Annotated[SceneConfig, _d("what the laser sees")]
    markers: Annotated[MarkersConfig | None, _d(
        "the markers; none (omitted or null): a marker-less scene, written without distances.csv (targetless "
        "calibration)")] = None
    tape: Annotated[TapeConfig, _d("the tape-measured marker distances (unused without markers)")] = TapeConfig()
    tolerances: Annotated[Tolerances, _d("what lrfsim run requires of the recovery")] = Tolerances()
    faults: Annotated[FaultsConfig, _d("faults injected into the recording (lrfsim.faults); none by default")] = (
        FaultsConfig())

    @model_validator(mode="after")
    def _check(self) -> Scenario:
        if self.markers is None:
            if self.faults.tape_outliers:
                raise ValueError("faults.tape_outliers needs markers (the scenario has none)")
            if self.faults.occluded_markers:
                raise ValueError("faults.occluded_markers needs markers (the scenario has none)")
            return self
        if self.markers.layout.kind == "board" and self.scene.board is None:
            raise ValueError("markers.layout is 'board' but scene.board is missing")
        if self.markers.layout.kind == "v" and self.scene.tunnel is None:
            raise ValueError("markers.layout is 'v' but scene.tunnel is missing")
        return self

    @property
    def marker_radius_m(self) -> float | None:
        """The markers' sphere radius [m]; None for a marker-less scene."""
        return None if self.markers is None else self.markers.radius_m


def _field_path(loc: tuple[int | str, ...]) -> str:
    """Dotted field path; drops the tag pydantic inserts after a discriminated union (markers.layout.v.x)."""
    parts: list[str] = []
    for i, p in enumerate(loc):
        if i > 0 and loc[i - 1] == "layout" and p in ("v", "board", "points"):
            continue
        if isinstance(p, int) and parts:
            parts[-1] += f"[{p}]"
            continue
        parts.append(str(p))
    return ".".join(parts) if parts else "(top level)"


def _models_in(annotation: object) -> list[type[BaseModel]]:
    """The pydantic models an annotation may hold (through Optional, unions and tuples)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    out: list[type[BaseModel]] = []
    for arg in get_args(annotation):
        out += _models_in(arg)
    return out


def _fields_at(loc: tuple[int | str, ...]) -> list[str]:
    """The valid keys of the section that holds the last element of a pydantic error location."""
    models: list[type[BaseModel]] = [Scenario]
    for part in loc[:-1]:
        if isinstance(part, int):
            continue
        tagged = [m for m in models if part in ("v", "board", "points") and
                  m.model_fields.get("kind") is not None and m.model_fields["kind"].default == part]
        if tagged:
            models = tagged
            continue
        nxt: list[type[BaseModel]] = []
        for m in models:
            if part in m.model_fields:
                nxt += _models_in(m.model_fields[part].annotation)
        models = nxt
    return sorted({f for m in models for f in m.model_fields})


def parse_scenario(data: object, source: str) -> Scenario:
    """Validate a scenario mapping; raise :class:`InputError` naming ``source``, the field and, for an unknown
    key, the nearest valid one."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        loc = tuple(err["loc"])
        field = _field_path(loc)
        value = err.get("input")
        msg = err["msg"]
        if err["type"] == "extra_forbidden" and loc:
            valid = _fields_at(loc)
            near = difflib.get_close_matches(str(loc[-1]), valid, n=1, cutoff=0.6)
            hint = f"did you mean {near[0]!r}? " if near else ""
            raise InputError(f"{source}: {field}: unknown key ({hint}valid keys: {', '.join(valid)})") from None
        if err["type"] == "finite_number":
            msg = "must be a finite number (NaN and infinity are not allowed)"
        shown = "" if isinstance(value, dict) else f" (got {value!r})"
        raise InputError(f"{source}: {field}: {msg}{shown}") from None


#: Memory a simulated beam costs over the whole run (simulation, recording, calibration; measured on tunnel_v:
#: 680 MB peak for 1.6 M beams) [bytes], and per footprint ray of a chunk of scans in flight [bytes].
BYTES_PER_BEAM = 320
BYTES_PER_CHUNK_RAY = 200
#: Refused above this estimate [bytes] (or 80 % of the machine's memory, if smaller).
MAX_SCENARIO_BYTES = 8 * 2**30


def estimate_memory_bytes(scenario: Scenario) -> tuple[int, int]:
    """(number of scans, bytes) a scenario needs: scans x beams x BYTES_PER_BEAM + a chunk's footprint rays."""
    from .profile import move_profile

    sv, se = scenario.servo, scenario.sensor
    move_s = move_profile(abs(sv.end_rad - sv.start_rad), sv.speed_rad_s, sv.accel_rad_s2)[0]
    duration_s = sv.settle_s + sv.passes * (move_s + sv.settle_s)
    n_scans = int(math.ceil(duration_s / se.scan_period_s)) + 1
    chunk_rays = 16 * se.n_beams * se.footprint_rays
    return n_scans, n_scans * se.n_beams * BYTES_PER_BEAM + chunk_rays * BYTES_PER_CHUNK_RAY


def _memory_limit_bytes() -> int:
    try:
        physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return MAX_SCENARIO_BYTES
    return int(min(MAX_SCENARIO_BYTES, 0.8 * physical))


def check_resources(scenario: Scenario, source: str) -> None:
    """Refuse a scenario whose recording would not fit in memory, with the estimate and its factors."""
    n_scans, need = estimate_memory_bytes(scenario)
    limit = _memory_limit_bytes()
    if need > limit:
        se = scenario.sensor
        raise InputError(
            f"{source}: sensor/servo: this scenario needs about {need / 2**30:.3g} GiB ({n_scans:,} scans x "
            f"{se.n_beams:,} beams x {BYTES_PER_BEAM} bytes; scan_period_s {se.scan_period_s:g}, servo.passes "
            f"{scenario.servo.passes}), more than the {limit / 2**30:.3g} GiB allowed: use fewer beams, passes or "
            "a longer scan_period_s")


def require_markers(scenario: Scenario, command: str, reason: str) -> None:
    """Refuse a marker-less scenario for ``command`` (e.g. "lrfsim plan"), which needs markers because of
    ``reason``: InputError naming the scenario and the ``markers`` section."""
    if scenario.markers is None:
        raise InputError(f"{scenario.name}: markers: the scenario has no markers; {command} {reason} "
                         "(`lrfsim simulate` writes its recording)")


def with_changes(data: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of a scenario mapping with dotted-key changes applied, e.g. ``{"servo.passes": 4}``
    (missing sections are created); validate the result with :func:`parse_scenario`."""
    out = copy.deepcopy(data)
    for key, value in changes.items():
        node = out
        *path, last = key.split(".")
        for k in path:
            node = node.setdefault(k, {})
        node[last] = value
    return out


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file. Relative mesh paths are resolved against the file's folder.

    Raises:
        InputError: unreadable or non-UTF-8 file, YAML syntax error (line and column), a field that is missing,
            unknown (the nearest valid key is suggested) or out of range, NaN or infinity, a recording that would
            not fit in memory.
    """
    path = Path(path)
    data = read_yaml(path, "scenario")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of sections (name, rig, scene, markers, ...), got "
                         f"{type(data).__name__}")
    scenario = parse_scenario(data, str(path))
    check_resources(scenario, str(path))
    if scenario.scene.meshes:
        meshes = tuple(
            m.model_copy(
                update={"file": m.file if m.file.is_absolute() else (path.parent / m.file).resolve()}
            )
            for m in scenario.scene.meshes
        )
        scenario = scenario.model_copy(update={"scene": scenario.scene.model_copy(update={"meshes": meshes})})
    return scenario


def scenario_inputs(scenario: Scenario, path: str | Path) -> dict[str, Path]:
    """The files a scenario reads, ``{label: path}``: the scenario file and its meshes (no output may overlap
    them)."""
    out: dict[str, Path] = {"scenario": Path(path)}
    for i, m in enumerate(scenario.scene.meshes):
        out[f"scene.meshes[{i}].file"] = Path(m.file)
    return out


def dump_scenario(scenario: Scenario) -> str:
    """The effective scenario (all defaults filled in) as YAML."""
    return yaml.safe_dump(scenario.model_dump(mode="json"), sort_keys=False)
