"""The sections of a scenario file (:mod:`lrfsim.scenario.file`) for the rig, the sensor, the servo, the tape, the
markers, the tolerances and the faults: one pydantic model per section, ``extra="forbid"``, bounds on every number,
every float finite. The scene's sections (what the laser sees) are in :mod:`lrfsim.scenario.scene_sections`.

Units are SI; angles in rad unless the field name says ``_deg``. Frames: W is the simulator world, z up, floor at
z = 0 (for a tunnel: x along the tunnel towards the plate, y to the left, walls at y = +-width/2; a room is placed in
W by its floor centre and yaw).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, model_validator

from lrfcal.io.rig import MAX_DH_TOLERANCE_M, MAX_DH_TOLERANCE_RAD
from lrfcal.model.kinematics import DH, Pose

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]


def doc(text: str, **kw: object) -> object:
    """A pydantic Field with a description (units in brackets) and optional bounds."""
    return Field(description=text, **kw)  # type: ignore[arg-type]


class Section(BaseModel):
    """The base of every section: unknown keys refused, frozen, every float finite."""

    # allow_inf_nan=False: every float of every section must be finite (NaN / inf name their field)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class DHConfig(Section):
    """DH parameters from the motor axis to the scan plane: T = Tx(a) Rx(alpha) Tz(b) Rz(beta)."""

    a: Annotated[float, doc("offset along the common normal [m]", ge=-0.5, le=0.5)]
    alpha: Annotated[float, doc("twist about the common normal [rad] (not degrees)", ge=-math.pi, le=math.pi)]
    b: Annotated[float, doc("offset along the new z axis [m]", ge=-0.5, le=0.5)]
    beta: Annotated[float, doc("rotation about the new z axis [rad] (not degrees)", ge=-math.pi, le=math.pi)]

    def to_dh(self) -> DH:
        return DH(self.a, self.alpha, self.b, self.beta)


class DHToleranceConfig(Section):
    """The design DH values' 1-sigma, written to nominal.yaml as ``dh_tolerance`` (lrfcal.io.rig.DHToleranceModel)."""

    a: Annotated[float, doc("a's 1-sigma [m]", gt=0, le=MAX_DH_TOLERANCE_M)]
    alpha: Annotated[float, doc("alpha's 1-sigma [rad] (not degrees)", gt=0, le=MAX_DH_TOLERANCE_RAD)]
    b: Annotated[float, doc("b's 1-sigma [m]", gt=0, le=MAX_DH_TOLERANCE_M)]
    beta: Annotated[float, doc("beta's 1-sigma [rad] (not degrees)", gt=0, le=MAX_DH_TOLERANCE_RAD)]


class PoseConfig(Section):
    """A pose: translation x, y, z [m], then R = Rz(yaw) Ry(pitch) Rx(roll) [rad] (as URDF)."""

    x: Annotated[float, doc("translation x [m]", ge=-100, le=100)] = 0.0
    y: Annotated[float, doc("translation y [m]", ge=-100, le=100)] = 0.0
    z: Annotated[float, doc("translation z [m]", ge=-100, le=100)] = 0.0
    roll: Annotated[float, doc("rotation about x, applied first [rad]", ge=-math.pi, le=math.pi)] = 0.0
    pitch: Annotated[float, doc("rotation about y [rad]", ge=-math.pi, le=math.pi)] = 0.0
    yaw: Annotated[float, doc("rotation about z, applied last [rad]", ge=-math.pi, le=math.pi)] = 0.0

    def to_pose(self) -> Pose:
        return Pose(self.x, self.y, self.z, self.roll, self.pitch, self.yaw)


class StandPartConfig(Section):
    """A solid box of the stand that holds the motor (a base plate, an upright, the motor's housing), fixed to the
    motor frame M: it moves with the rig's mount, not with the motor's turn, and the laser sees it (unlike the rig's
    own servo and scanner housing, which it never sees): a tilting scanner looks down at its stand at large tilts."""

    pose: Annotated[PoseConfig, doc("pose of the part's centre in the motor frame M (z_M the motor axis; the true "
                                    "frame, as the part is built onto the motor)")]
    size_x_m: Annotated[float, doc("edge length along the part's local x [m]", gt=0, le=10)]
    size_y_m: Annotated[float, doc("edge length along the part's local y [m]", gt=0, le=10)]
    size_z_m: Annotated[float, doc("edge length along the part's local z [m]", gt=0, le=10)]
    reflectivity: Annotated[float, doc("Lambertian albedo of its faces [1]", ge=0, le=1)] = 0.5


class RigConfig(Section):
    """The rig: true DH and mount pose (ground truth) and the design-drawing (nominal) values; optionally the stand
    that holds the motor, as geometry the laser sees."""

    dh: Annotated[DHConfig, doc("true DH parameters (ground truth)")]
    mount: Annotated[PoseConfig, doc("true mount pose T_W_M of the motor frame M in W (ground truth)")]
    nominal_dh: Annotated[DHConfig, doc("design DH values written to nominal.yaml (the calibration's start)")]
    nominal_mount: Annotated[PoseConfig, doc("design mount pose written to nominal.yaml")]
    nominal_dh_tolerance: Annotated[DHToleranceConfig | None, doc(
        "the design DH values' 1-sigma written to nominal.yaml (none: left out, the calibration's default 10 mm and "
        "5 deg; a drawn truth writes the spread it is drawn with)")] = None
    stand: Annotated[tuple[StandPartConfig, ...], doc(
        "the stand's parts, boxes fixed to the motor frame M that the laser sees (none by default: only the scene "
        "is seen)")] = ()


class NoiseBand(Section):
    """Range noise below ``up_to_m``: Gaussian with ``sigma_m`` (Hokuyo spec: repeatability sigma)."""

    up_to_m: Annotated[float, doc("upper range of this band [m]", gt=0, le=1000)]
    sigma_m: Annotated[float, doc("range noise 1-sigma in this band (a scanner's is millimetres to centimetres) [m]",
                                  ge=0, le=1)]


class IntensityConfig(Section):
    """Intensity model (see lrfsim.sensors.lidar): counts = gain * rho * g(theta) * (r_ref / r)^2, saturated."""

    gain_counts: Annotated[float, doc("counts of a rho = 1 Lambertian target at ref_range_m, normal incidence "
                                      "[counts]", gt=0)] = 4000.0
    ref_range_m: Annotated[float, doc("reference range of gain_counts [m]", gt=0, le=1000)] = 1.0
    saturation_counts: Annotated[float, doc("largest intensity reported [counts]", gt=0, le=1e9)] = 65535.0
    relative_noise: Annotated[float, doc("multiplicative intensity noise, 1-sigma [1]", ge=0, le=1)] = 0.05
    min_detectable_counts: Annotated[float, doc("weaker returns are dropped (no return) [counts]", ge=0, le=1e9)] = 20.0


#: Published characterisations the systematic-error defaults refer to (docs/sensor_errors.md).
_REFS = ("Kneip et al. ICRA 2009 (URG-04LX); Okubo et al. 2009 (URG-04LX); Ye & Borenstein ICRA 2002 "
         "(LMS 200); Pomerleau et al. CARPI 2012 (UTM-30LX)")


class SystematicConfig(Section):
    """Systematic range errors of the scanner (lrfsim.sensors.lidar, docs/sensor_errors.md), all off by default: the
    papers that characterise them (Kneip et al. 2009, Okubo et al. 2009, Pomerleau et al. 2012, Ye & Borenstein
    2002) show each effect, but no figure for the UTM-30LX-EW could be read for this model, so every value
    here is assumed. Added to each return before noise and quantisation:
    b = range_offset_m + intensity_bias_m_per_decade * log10(min(I, saturation) / intensity_ref_counts)
    + incidence_bias_m * theta / (1 rad) + drift_amplitude_m * exp(-(drift_elapsed_s + t) / drift_time_constant_s)
    + beam_wiggle_m * sin(2 pi i / beam_wiggle_period_beams) + range_wiggle_m * sin(2 pi r / range_wiggle_period_m),
    I the return's noise-free intensity, theta the incidence angle of each footprint sub-ray, t the beam's
    time from the start of the sweep, i the beam's index in its scan, r its noise-free range."""

    range_offset_m: Annotated[float, doc("constant added to every range (the spec's +-30 mm accuracy bounds it; "
                                         "0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    intensity_bias_m_per_decade: Annotated[float, doc(
        "range bias per decade of received intensity (range walk: bright retroreflectors read short when < 0; "
        "observed by " + _REFS + "; 0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    intensity_ref_counts: Annotated[float, doc("intensity at which the intensity bias is zero [counts]", gt=0, le=1e9)
                                    ] = 1000.0
    incidence_bias_m: Annotated[float, doc(
        "range bias per radian of incidence angle (the bias at 1 rad; b = incidence_bias_m * theta / 1 rad), per "
        "footprint sub-ray (observed by " + _REFS + "; 0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    drift_amplitude_m: Annotated[float, doc(
        "warm-up drift at power-on, decaying exponentially (time drift observed by Kneip et al. 2009 and Ye & "
        "Borenstein 2002; 0 = off, value assumed) [m]", ge=-1, le=1)] = 0.0
    drift_time_constant_s: Annotated[float, doc("time constant of the warm-up drift (assumed) [s]", gt=0, le=1e6)
                                     ] = 1200.0
    drift_elapsed_s: Annotated[float, doc("time from power-on to the start of the sweep [s]", ge=0, le=1e6)] = 0.0
    beam_wiggle_m: Annotated[float, doc(
        "amplitude of a range bias that wiggles along the scan, the same in every scan: a sine of the beam index "
        "(on the real URG-04LX box recording, the facing wall's residual averaged per beam over 1599 scans wiggles "
        "with about 1.2 mm at a period of about 61 beams, docs/real-data.md; 0 = off) [m]", ge=-0.1, le=0.1)] = 0.0
    beam_wiggle_period_beams: Annotated[float, doc("period of that wiggle, in beams [1]", gt=0, le=100000)] = 61.0
    range_wiggle_m: Annotated[float, doc(
        "amplitude of a range bias periodic in the range, a sine of the noise-free range (the cyclic error of a "
        "phase-shift rangefinder such as the URG-04LX; 0 = off, value assumed) [m]", ge=-0.1, le=0.1)] = 0.0
    range_wiggle_period_m: Annotated[float, doc("period of that wiggle, in range [m]", gt=0, le=1000)] = 0.5


class EchoesConfig(Section):
    """Multi-echo returns (the UTM-30LX-EW reports up to 3 echoes per beam; urg_node with publish_multiecho
    publishes them as sensor_msgs/MultiEchoLaserScan on ``echoes``). Footprint sub-rays are grouped by range:
    sorted by range, a gap wider than ``separation_m`` starts a new echo; each echo is the power-weighted mean
    of its group (lrfsim.sensors.lidar). Off by default (no echoes topic written)."""

    enabled: Annotated[bool, doc("write the echoes topic beside /scan")] = False
    topic: Annotated[str, doc("topic of the MultiEchoLaserScan messages", min_length=1)] = "/echoes"
    separation_m: Annotated[float, doc("sub-ray ranges further apart than this are separate echoes (value "
                                       "assumed) [m]", gt=0, le=100)] = 0.1
    max_echoes: Annotated[int, doc("echoes kept per beam, nearest first (UTM-30LX-EW: 3) [1]", ge=1, le=8)] = 3


class SensorConfig(Section):
    """The scanner; defaults: the Hokuyo UTM-30LX-EW (spec sheet: 270 deg in 0.25 deg steps, 25 ms per scan,
    0.023-60 m, repeatability 10 mm below 10 m and 30 mm below 30 m; LaserScan fields as urg_node fills them)."""

    n_beams: Annotated[int, doc("beams per scan [1]", ge=2, le=100000)] = 1081
    angle_min_rad: Annotated[float, doc("bearing of beam 0 (LaserScan angle_min) [rad]", ge=-math.pi,
                                        le=math.pi)] = -2.356194490192345
    angle_increment_rad: Annotated[float, doc("bearing step between beams [rad]", gt=0, le=math.pi)
                                   ] = 2 * math.pi / 1440
    scan_period_s: Annotated[float, doc("time from one scan to the next (LaserScan scan_time) [s]", gt=0, le=10)
                             ] = 0.025
    time_increment_s: Annotated[float, doc("time between beams (LaserScan time_increment) [s]", gt=0, le=1)
                                ] = 0.025 / 1440
    range_min_m: Annotated[float, doc("shortest range reported [m]", gt=0, le=1000)] = 0.023
    range_max_m: Annotated[float, doc("longest range reported [m]", gt=0, le=1000)] = 60.0
    no_return: Annotated[Literal["nan", "inf"], doc("value written for a beam without return")] = "nan"
    noise: Annotated[bool, doc("add range and intensity noise")] = True
    noise_bands: Annotated[tuple[NoiseBand, ...], doc("range noise by range band, in increasing up_to_m")] = (
        NoiseBand(up_to_m=10.0, sigma_m=0.010),
        NoiseBand(up_to_m=30.0, sigma_m=0.030),
        NoiseBand(up_to_m=60.0, sigma_m=0.050),
    )
    noise_range_fraction: Annotated[float, doc(
        "range-proportional noise: the range noise sigma is at least this fraction of the range, sigma(r) = "
        "max(the band's sigma_m, noise_range_fraction x r) (the URG-04LX datasheet's accuracy: +-10 mm to 1 m, 1 % of "
        "the range beyond; 0: the bands alone) [1]", ge=0, le=0.1)] = 0.0
    noise_correlation: Annotated[float, doc(
        "correlation of the range noise of neighbouring beams in a scan: an AR(1) process along the beams, rho^k "
        "at k beams apart (0: independent; measured 0.70 on a real URG-04LX, docs/real-data.md; no public figure "
        "for the UTM-30LX-EW, so 0 by default) [1]", ge=0, lt=1)] = 0.0
    quantisation_m: Annotated[float, doc("range resolution (0: none) [m]", ge=0, le=1)] = 0.001
    divergence_rad: Annotated[float, doc("full beam divergence angle; unverified for the UTM-30LX, see "
                                         "docs/simulator.md [rad]", ge=0, lt=0.1)] = 0.0044
    footprint_rays: Annotated[int, doc("rays per beam footprint (1: centre ray only) [1]", ge=1, le=64)] = 7
    footprint_cast: Annotated[Literal["edges", "full"], doc(
        "where the footprint's ring of sub-rays is cast: edges = only where it can change a beam (where neighbouring "
        "beams differ, near a marker, at a scan's ends), elsewhere the sub-rays meet the centre ray's tangent plane, "
        "exact on planes (of 1.6 million beams 0 differ on tunnel_v and spinning_tilted, 6 on room_box, 62 on "
        "plane_30deg; lrfsim.cast.chunks.cast_chunk_edges); full = every sub-ray of every beam (2.4x the "
        "simulation's time on tunnel_v, one thread)")
                              ] = "edges"
    intensity: Annotated[IntensityConfig, doc("intensity model")] = IntensityConfig()
    systematic: Annotated[SystematicConfig, doc("systematic range errors (all off by default; "
                                                "docs/sensor_errors.md)")] = SystematicConfig()
    echoes: Annotated[EchoesConfig, doc("multi-echo returns on a MultiEchoLaserScan topic (off by default)")] = (
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


class ServoConfig(Section):
    """The servo's motion (lrfsim.sensors.servo): ``mode: sweep`` turns from ``start_rad`` to ``end_rad`` at
    ``speed_rad_s``, ``passes`` times (alternating); ``mode: spin`` turns continuously one way for ``revolutions`` full
    turns from ``start_rad`` (a continuous joint: the joint states carry the unwrapped angle, beyond +-pi); ``mode:
    step`` steps from ``start_rad`` to ``end_rad`` in steps of ``step_rad`` and stands still while the laser scans
    (step and scan, as a stepper tilt stand: one step and one scan every ``step_period_s``, one joint state per scan
    at the scan's stamp; the recording's rig file says ``servo.motion: step``)."""

    joint: Annotated[str, doc("joint name in the JointState messages (as the rig file's servo.joint; the old key "
                              "joint_name is still read)", min_length=1,
                              validation_alias=AliasChoices("joint", "joint_name"))] = "servo"
    mode: Annotated[Literal["sweep", "spin", "step"], doc(
        "sweep: back and forth between start_rad and end_rad; spin: one way for `revolutions` full turns from "
        "start_rad (accelerate, cruise, decelerate and stop; the ramps count in the turns), end_rad not used; "
        "step: step and scan between start_rad and end_rad (step_rad, step_period_s), back and forth as a sweep")
                    ] = "sweep"
    start_rad: Annotated[float, doc("motor angle where the motion starts [rad]", ge=-2 * math.pi, le=2 * math.pi)
                         ] = math.pi / 2
    end_rad: Annotated[float, doc("motor angle where the first pass ends (modes sweep and step; not used with mode "
                                  "spin) [rad]", ge=-2 * math.pi, le=2 * math.pi)] = -math.pi / 2
    revolutions: Annotated[float, doc("mode spin: full turns from start to stop, ramps included (may be "
                                      "fractional; not used with mode sweep) [1]", gt=0, le=1000)] = 1.0
    spin_direction: Annotated[Literal[1, -1], doc("mode spin: +1 turns towards increasing motor angle, -1 "
                                                  "towards decreasing [1]")] = 1
    step_rad: Annotated[float, doc(
        "mode step: the turn of one step; |end_rad - start_rad| must be a whole number of steps (the URG-04LX stand "
        "of github.com/liangfok/tilting_lidar_scanner: 360 / 4800 deg = 0.075 deg, its Arduino program's "
        "STEPS_PER_REV) [rad]", gt=0, le=math.pi / 4)] = math.radians(0.075)
    step_period_s: Annotated[float, doc(
        "mode step: time from one step to the next; one scan per step, so it must equal sensor.scan_period_s, and "
        "the step's move (speed_rad_s, accel_rad_s2) must fit in the time the laser does not scan: the scans are "
        "timed to stand still, each centred in its step's standstill [s]", gt=0, le=10)] = 0.1
    speed_rad_s: Annotated[float, doc("cruise speed (mode step: of each step's move) [rad/s]", gt=0, le=10)
                           ] = math.radians(10.0)
    accel_rad_s2: Annotated[float, doc("acceleration of the trapezoidal ramps (mode step: of each step's move) "
                                       "[rad/s^2]", gt=0, le=1000)] = 2.0
    passes: Annotated[int, doc("number of passes, alternating direction (mode spin: must be 1) [1]", ge=1, le=100)
                      ] = 1
    settle_s: Annotated[float, doc("standing still at each end (mode step: a whole number of step_period_s) [s]",
                                   ge=0, le=3600)] = 0.2
    rate_hz: Annotated[float, doc("JointState publishing rate (mode step: not used, one joint state per scan, "
                                  "stamped with the scan's stamp, as the stand reports its angle with each scan) "
                                  "[Hz]", gt=0, le=10000)] = 100.0
    encoder_counts: Annotated[int, doc("encoder counts per revolution (0: no quantisation) [1]", ge=0, le=2**30)] = 4096
    backlash_rad: Annotated[float, doc("gear play, total width (play operator) [rad]", ge=0, le=math.pi / 4)] = 0.0
    clock_offset_s: Annotated[float, doc("laser stamp minus servo stamp of the same instant [s]", ge=-1, le=1)
                              ] = 0.0

    @model_validator(mode="after")
    def _check(self) -> ServoConfig:
        if self.mode == "spin":
            if self.passes != 1:
                raise ValueError(f"passes is {self.passes}: a spin (mode spin) turns one way, passes must be 1 "
                                 "(more turns: revolutions)")
        elif self.start_rad == self.end_rad:
            raise ValueError(f"start_rad and end_rad are equal ({self.start_rad}): nothing to sweep")
        if self.mode == "step":
            steps = abs(self.end_rad - self.start_rad) / self.step_rad
            if abs(steps - round(steps)) > 1e-6:
                raise ValueError(f"mode step: |end_rad - start_rad| is {steps:.6g} steps of step_rad "
                                 f"{self.step_rad:.6g} rad: it must be a whole number of steps")
            holds = self.settle_s / self.step_period_s
            if abs(holds - round(holds)) > 1e-6:
                raise ValueError(f"mode step: settle_s {self.settle_s:g} s must be a whole number of step_period_s "
                                 f"({self.step_period_s:g} s), so that every scan stands still")
        return self


class TapeConfig(Section):
    """The person with the tape: Gaussian noise on each measured pair; optionally only some pairs."""

    sigma_m: Annotated[float, doc("tape noise 1-sigma per measured distance [m]", ge=0, le=1)] = 0.001
    pair_fraction: Annotated[float, doc("fraction of marker pairs measured (seeded choice) [1]", gt=0, le=1)] = 1.0


class VLayout(Section):
    """Markers in a V on the tunnel walls: per wall, two arms meeting at the apex (lowest point)."""

    kind: Annotated[Literal["v"], doc("layout selector")] = "v"
    walls: Annotated[tuple[Literal["left", "right"], ...], doc("walls with a V")] = ("left", "right")
    x_start_m: Annotated[float, doc("x in W where the V starts [m]")] = 0.3
    x_end_m: Annotated[float, doc("x in W where the V ends [m]")] = 1.9
    z_apex_m: Annotated[float, doc("height of the apex [m]")] = 0.5
    z_top_m: Annotated[float, doc("height of the arms' ends [m]")] = 1.9
    per_arm: Annotated[int, doc("markers per arm, apex included [1]", ge=1, le=50)] = 4
    jitter_m: Annotated[float, doc("random offsets along the wall and in height (seeded), so the arms are not "
                                   "perfectly straight, as hand-placed markers are not [m]", ge=0, le=1)] = 0.0


class BoardLayout(Section):
    """Markers in a grid on the board's front face (requires scene.board)."""

    kind: Annotated[Literal["board"], doc("layout selector")] = "board"
    rows: Annotated[int, doc("grid rows [1]", ge=1, le=50)] = 4
    cols: Annotated[int, doc("grid columns [1]", ge=1, le=50)] = 5
    spacing_m: Annotated[float, doc("grid spacing [m]", gt=0, le=10)] = 0.2
    jitter_m: Annotated[float, doc("random in-plane offsets (seeded), so the grid is not perfectly regular [m]",
                                   ge=0, le=1)] = 0.0


class PointsLayout(Section):
    """Markers at explicit sphere-centre positions in W."""

    kind: Annotated[Literal["points"], doc("layout selector")] = "points"
    positions: Annotated[tuple[tuple[float, float, float], ...], doc("sphere centres [x, y, z] in W [m]")]


class MarkersConfig(Section):
    """The retroreflective sphere markers: size and layout."""

    radius_m: Annotated[float, doc("sphere radius [m]", gt=0, le=0.2)] = 0.005
    layout: Annotated[VLayout | BoardLayout | PointsLayout,
                      doc("where the markers are: kind v, board or points", discriminator="kind")]


class Tolerances(Section):
    """What `lrfsim run` requires of the recovery (absolute errors)."""

    a_m: Annotated[float, doc("error of a [m]", gt=0)] = 0.0005
    b_m: Annotated[float, doc("error of b [m]", gt=0)] = 0.0005
    alpha_rad: Annotated[float, doc("error of alpha [rad]", gt=0)] = math.radians(0.02)
    beta_rad: Annotated[float, doc("error of beta [rad]", gt=0)] = math.radians(0.02)
    position_m: Annotated[float, doc("error of the mount position [m]", gt=0)] = 0.005
    rotation_rad: Annotated[float, doc("error of the mount rotation (angle) [rad]", gt=0)] = math.radians(0.2)
    tunnel_m: Annotated[float, doc("error of the tunnel dimensions from the calibrated cloud [m]", gt=0)] = 0.003


class TapeOutlier(Section):
    """A misread tape: ``error_m`` added to one measured pair, named by its two marker ids ([id_i, id_j], either
    order) or by its row index in distances.csv."""

    pair: Annotated[tuple[str, str] | Annotated[int, Field(ge=0)],
                    doc("the pair: its two marker ids [id_i, id_j] or its row in distances.csv [1]")]
    error_m: Annotated[float, doc("added to the measured distance [m]", ge=-10, le=10)]


class FaultsConfig(Section):
    """Faults injected into the recording (lrfsim.simulation.faults), all off by default. Applied to the simulated
    arrays before writing, seeded from ``seed`` with a stream of their own, and listed in ground_truth.yaml under
    ``faults``. The laser-servo clock offset is ``servo.clock_offset_s`` (laser stamp - servo stamp), which the
    recording does not declare to the calibration."""

    tape_outliers: Annotated[tuple[TapeOutlier, ...], doc("misread tape distances (distances.csv)")] = ()
    inverted_servo: Annotated[bool, doc("joint positions and velocities negated: a servo mounted the other way "
                                        "round; the truth is unchanged")] = False
    false_blobs: Annotated[int, doc("bright spots (retroreflector-like intensity) on non-marker surfaces, each "
                                    "1-3 scans x 2-4 beams [1]", ge=0, le=200)] = 0
    occluded_markers: Annotated[int, doc("markers whose returns are removed (range and intensity those of the "
                                         "surface around, as if covered) [1]", ge=0, le=1000)] = 0
    dropped_scans_fraction: Annotated[float, doc("fraction of the scans left out of the bag (random scans) [1]",
                                                 ge=0, le=0.9)] = 0.0
    encoder_spikes: Annotated[int, doc("joint-state samples whose position jumps by +-encoder_spike_rad (random "
                                       "sign) [1]", ge=0, le=100000)] = 0
    encoder_spike_rad: Annotated[float, doc("size of an encoder spike [rad]", gt=0, le=math.pi)] = 0.5
    range_noise_scale: Annotated[float, doc("every range noise band's sigma times this, applied before "
                                            "simulating [1]", ge=0, le=100)] = 1.0
    stamp_latency_s: Annotated[float, doc("scan stamps taken at receive time: each stamp this much later than its "
                                          "first beam [s]", ge=0, le=1)] = 0.0
    stamp_jitter_s: Annotated[float, doc("and a further uniform random delay in [0, this) per scan [s]", ge=0,
                                        le=1)] = 0.0
    gear_ratio: Annotated[float, doc("joint positions and velocities published times this (a wrong gear ratio or "
                                     "counts per revolution in the driver; 1: off); the truth is unchanged [1]",
                                     gt=0, le=100)] = 1.0
    joint_rate_hz: Annotated[float | None, doc("joint states thinned to at most this rate, every n-th sample kept "
                                               "with n = ceil(servo.rate_hz / this) (a servo polled slowly; null: "
                                               "off) [Hz]", gt=0, le=10000)] = None
    joint_gap_s: Annotated[float | None, doc("the joint states of this long a time removed (a stalled joint-state "
                                             "stream; null: off) [s]", gt=0, le=3600)] = None
    joint_gap_at_s: Annotated[float | None, doc("the middle of that gap on the servo clock (t = 0: the start of the "
                                                "motion; null: the middle of the servo's first turnaround) [s]",
                                                ge=0)] = None
    range_scale: Annotated[float, doc("every reported range times this (a scanner whose range scale is off; 1: off); "
                                      "the truth is unchanged [1]", gt=0.5, le=2)] = 1.0
    angle_increment_off_by_one: Annotated[bool, doc(
        "the LaserScans declare angle_increment = (angle_max - angle_min) / N instead of / (N - 1) (a driver's "
        "off-by-one, N beams); angle_min, angle_max and the ranges are unchanged")] = False
    joint_clock_step_s: Annotated[float | None, doc(
        "the servo computer's clock steps by this much (negative: back, as an NTP correction) at "
        "joint_clock_step_at_s: every later JointState stamp moved by it, the bag's receive times not (null: off) "
        "[s]", ge=-3600, le=3600)] = None
    joint_clock_step_at_s: Annotated[float | None, doc(
        "when the servo clock steps (true servo-clock time, t = 0: the start of the motion; null: the middle of the "
        "joint states) [s]", ge=0)] = None
    scan_clock_step_s: Annotated[float | None, doc(
        "the laser's clock steps by this much at scan_clock_step_at_s: every later LaserScan stamp moved by it, "
        "the bag's receive times not (null: off) [s]", ge=-3600, le=3600)] = None
    scan_clock_step_at_s: Annotated[float | None, doc(
        "when the laser clock steps (true laser-clock time; null: the middle of the scans) [s]", ge=0)] = None
