"""Scenario files: one pydantic model per section, ``extra="forbid"``, bounds on every number.

A scenario fully determines a simulated recording (with its seed). Units are SI; angles in rad unless the
field name says ``_deg``. Frames: W is the simulator world (the tunnel frame: x along the tunnel towards the
plate, y to the left, z up, floor at z = 0, walls at y = +-width/2).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from lrfcal.errors import InputError
from lrfcal.kinematics import DH, Pose

PositiveFloat = Annotated[float, Field(gt=0)]
NonNegFloat = Annotated[float, Field(ge=0)]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class DHConfig(_Section):
    """DH parameters a [m], alpha [rad], b [m], beta [rad]."""

    a: Annotated[float, Field(ge=-0.5, le=0.5)]
    alpha: Annotated[float, Field(ge=-math.pi, le=math.pi)]
    b: Annotated[float, Field(ge=-0.5, le=0.5)]
    beta: Annotated[float, Field(ge=-math.pi, le=math.pi)]

    def to_dh(self) -> DH:
        return DH(self.a, self.alpha, self.b, self.beta)


class PoseConfig(_Section):
    """A pose: translation x, y, z [m], then R = Rz(yaw) Ry(pitch) Rx(roll) [rad]."""

    x: Annotated[float, Field(ge=-100, le=100)] = 0.0
    y: Annotated[float, Field(ge=-100, le=100)] = 0.0
    z: Annotated[float, Field(ge=-100, le=100)] = 0.0
    roll: Annotated[float, Field(ge=-math.pi, le=math.pi)] = 0.0
    pitch: Annotated[float, Field(ge=-math.pi, le=math.pi)] = 0.0
    yaw: Annotated[float, Field(ge=-math.pi, le=math.pi)] = 0.0

    def to_pose(self) -> Pose:
        return Pose(self.x, self.y, self.z, self.roll, self.pitch, self.yaw)


class RigConfig(_Section):
    """The rig: true DH and mount pose (ground truth) and the design-drawing (nominal) values."""

    dh: DHConfig
    mount: PoseConfig
    nominal_dh: DHConfig
    nominal_mount: PoseConfig


class NoiseBand(_Section):
    """Range noise below ``up_to_m``: Gaussian with ``sigma_m`` (Hokuyo spec: repeatability sigma)."""

    up_to_m: PositiveFloat
    sigma_m: NonNegFloat


class IntensityConfig(_Section):
    """Intensity model (see lrfsim.lidar): counts = gain * rho * g(theta) * (r_ref / r)^2, saturated."""

    gain_counts: PositiveFloat = 4000.0  # a rho = 1 Lambertian target at r_ref, normal incidence
    ref_range_m: PositiveFloat = 1.0
    saturation_counts: PositiveFloat = 65535.0
    relative_noise: Annotated[float, Field(ge=0, le=1)] = 0.05
    min_detectable_counts: NonNegFloat = 20.0


class SensorConfig(_Section):
    """Hokuyo UTM-30LX-EW defaults (FACTS.md)."""

    n_beams: Annotated[int, Field(ge=2, le=100000)] = 1081
    angle_min_rad: Annotated[float, Field(ge=-math.pi, le=math.pi)] = -2.356194490192345
    angle_increment_rad: PositiveFloat = 2 * math.pi / 1440
    scan_period_s: PositiveFloat = 0.025
    time_increment_s: PositiveFloat = 0.025 / 1440
    range_min_m: PositiveFloat = 0.023
    range_max_m: PositiveFloat = 60.0
    no_return: Literal["nan", "inf"] = "nan"
    noise: bool = True
    noise_bands: tuple[NoiseBand, ...] = (
        NoiseBand(up_to_m=10.0, sigma_m=0.010),
        NoiseBand(up_to_m=30.0, sigma_m=0.030),
        NoiseBand(up_to_m=60.0, sigma_m=0.050),
    )
    quantisation_m: NonNegFloat = 0.001
    divergence_rad: NonNegFloat = 0.0044  # full angle; unverified for the UTM-30LX, see README
    footprint_rays: Annotated[int, Field(ge=1, le=64)] = 7
    intensity: IntensityConfig = IntensityConfig()

    @model_validator(mode="after")
    def _check(self) -> SensorConfig:
        if self.range_min_m >= self.range_max_m:
            raise ValueError(f"range_min_m {self.range_min_m} must be below range_max_m {self.range_max_m}")
        return self


class ServoConfig(_Section):
    """The servo sweep: from ``start_rad`` to ``end_rad`` at ``speed_rad_s``, ``passes`` times (alternating)."""

    joint_name: str = "servo"
    start_rad: Annotated[float, Field(ge=-2 * math.pi, le=2 * math.pi)] = math.pi / 2
    end_rad: Annotated[float, Field(ge=-2 * math.pi, le=2 * math.pi)] = -math.pi / 2
    speed_rad_s: Annotated[float, Field(gt=0, le=10)] = math.radians(10.0)
    accel_rad_s2: Annotated[float, Field(gt=0, le=1000)] = 2.0  # trapezoidal ramps (0.09 s at 10 deg/s)
    passes: Annotated[int, Field(ge=1, le=100)] = 1
    settle_s: NonNegFloat = 0.2  # standing still at each end
    rate_hz: Annotated[float, Field(gt=0, le=10000)] = 100.0
    encoder_counts: Annotated[int, Field(ge=0)] = 4096  # 0: no quantisation
    backlash_rad: NonNegFloat = 0.0
    clock_offset_s: Annotated[float, Field(ge=-1, le=1)] = 0.0  # laser stamp - servo stamp, same instant

    @model_validator(mode="after")
    def _check(self) -> ServoConfig:
        if self.start_rad == self.end_rad:
            raise ValueError(f"start_rad and end_rad are equal ({self.start_rad}): nothing to sweep")
        return self


class TapeConfig(_Section):
    """The person with the tape: Gaussian noise on each measured pair; optionally only some pairs."""

    sigma_m: NonNegFloat = 0.001
    pair_fraction: Annotated[float, Field(gt=0, le=1)] = 1.0


class MaterialsConfig(_Section):
    """Lidar reflectivity per surface class (Lambertian albedo; retroreflector as an effective gain)."""

    painted_steel: Annotated[float, Field(ge=0, le=1)] = 0.35
    retroreflector: Annotated[float, Field(ge=0, le=10000)] = 200.0
    board: Annotated[float, Field(ge=0, le=1)] = 0.6


class ManholeConfig(_Section):
    """A rectangular opening in the plate, centred at (y, z) in W."""

    width_m: PositiveFloat = 0.40
    height_m: PositiveFloat = 0.60
    center_y_m: float = 0.0
    center_z_m: float = 1.15


class TunnelConfig(_Section):
    """A box-girder tunnel: floor z = 0, ceiling z = height, walls y = +-width/2, plate at x = plate_x_m."""

    width_m: PositiveFloat = 0.78
    height_m: PositiveFloat = 2.30
    x_min_m: float = -1.0
    plate_x_m: float = 2.24
    wall_thickness_m: PositiveFloat = 0.01
    manhole: ManholeConfig | None = None

    @model_validator(mode="after")
    def _check(self) -> TunnelConfig:
        if self.x_min_m >= self.plate_x_m:
            raise ValueError(f"x_min_m {self.x_min_m} must be behind plate_x_m {self.plate_x_m}")
        return self


class BoardConfig(_Section):
    """A planar board (thin box) with its centre and orientation; its front face is its local +z."""

    pose: PoseConfig
    width_m: PositiveFloat = 1.5
    height_m: PositiveFloat = 1.0
    thickness_m: PositiveFloat = 0.01


class MeshConfig(_Section):
    """Extra geometry from an STL/OBJ file (loaded with trimesh), placed at ``pose`` in W."""

    file: Path
    pose: PoseConfig = PoseConfig()
    scale: PositiveFloat = 1.0
    reflectivity: Annotated[float, Field(ge=0, le=10000)] = 0.35


class SceneConfig(_Section):
    tunnel: TunnelConfig | None = None
    board: BoardConfig | None = None
    meshes: tuple[MeshConfig, ...] = ()
    materials: MaterialsConfig = MaterialsConfig()


class VLayout(_Section):
    """Markers in a V on the tunnel walls: per wall, two arms meeting at the apex (lowest point)."""

    kind: Literal["v"] = "v"
    walls: tuple[Literal["left", "right"], ...] = ("left", "right")
    x_start_m: float = 0.3
    x_end_m: float = 1.9
    z_apex_m: float = 0.5
    z_top_m: float = 1.9
    per_arm: Annotated[int, Field(ge=1, le=50)] = 4


class BoardLayout(_Section):
    """Markers in a grid on the board's front face (requires scene.board)."""

    kind: Literal["board"] = "board"
    rows: Annotated[int, Field(ge=1, le=50)] = 4
    cols: Annotated[int, Field(ge=1, le=50)] = 5
    spacing_m: PositiveFloat = 0.2
    jitter_m: NonNegFloat = 0.0  # random in-plane offsets (seeded), so the grid is not perfectly regular


class PointsLayout(_Section):
    """Markers at explicit sphere-centre positions in W."""

    kind: Literal["points"] = "points"
    positions: tuple[tuple[float, float, float], ...]


class MarkersConfig(_Section):
    radius_m: Annotated[float, Field(gt=0, le=0.2)] = 0.005
    layout: VLayout | BoardLayout | PointsLayout = Field(discriminator="kind")


class Tolerances(_Section):
    """What `lrfsim run` requires of the recovery (absolute errors)."""

    a_m: PositiveFloat = 0.0005
    b_m: PositiveFloat = 0.0005
    alpha_rad: PositiveFloat = math.radians(0.02)
    beta_rad: PositiveFloat = math.radians(0.02)
    position_m: PositiveFloat = 0.005
    rotation_rad: PositiveFloat = math.radians(0.2)
    tunnel_m: PositiveFloat = 0.003


class Scenario(_Section):
    name: str
    seed: Annotated[int, Field(ge=0)] = 0
    rig: RigConfig
    sensor: SensorConfig = SensorConfig()
    servo: ServoConfig = ServoConfig()
    scene: SceneConfig
    markers: MarkersConfig
    tape: TapeConfig = TapeConfig()
    tolerances: Tolerances = Tolerances()

    @model_validator(mode="after")
    def _check(self) -> Scenario:
        if self.markers.layout.kind == "board" and self.scene.board is None:
            raise ValueError("markers.layout is 'board' but scene.board is missing")
        if self.markers.layout.kind == "v" and self.scene.tunnel is None:
            raise ValueError("markers.layout is 'v' but scene.tunnel is missing")
        return self


def _field_path(loc: tuple[int | str, ...]) -> str:
    """Dotted field path; drops the tag pydantic inserts after a discriminated union (markers.layout.v.x)."""
    parts: list[str] = []
    for i, p in enumerate(loc):
        if i > 0 and loc[i - 1] == "layout" and p in ("v", "board", "points"):
            continue
        parts.append(str(p))
    return ".".join(parts) if parts else "(top level)"


def parse_scenario(data: object, source: str) -> Scenario:
    """Validate a scenario mapping; raise :class:`InputError` naming ``source`` and the field."""
    try:
        return Scenario.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        field = _field_path(tuple(err["loc"]))
        value = err.get("input")
        msg = err["msg"]
        shown = "" if isinstance(value, dict) else f" (got {value!r})"
        raise InputError(f"{source}: {field}: {msg}{shown}") from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file. Relative mesh paths are resolved against the file's folder."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise InputError(f"{path}: cannot read scenario ({e.strerror})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(f"{path}: not valid YAML ({str(e).splitlines()[0]})") from None
    scenario = parse_scenario(data, str(path))
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
