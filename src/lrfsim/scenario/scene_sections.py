"""The scene's sections of a scenario file (:mod:`lrfsim.scenario.file`): what the laser sees, a tunnel, a room, a
board, boxes, cylinders, spheres and meshes, and their reflectivities; the rig's, sensor's and markers' sections are
in :mod:`lrfsim.scenario.sections`.

Units are SI; angles in rad unless the field name says ``_deg``. Frames: W is the simulator world, z up, floor at
z = 0 (for a tunnel: x along the tunnel towards the plate, y to the left, walls at y = +-width/2; a room is placed in
W by its floor centre and yaw).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

from pydantic import model_validator

from .sections import PoseConfig, Section, doc


class MaterialsConfig(Section):
    """Lidar reflectivity per surface class (Lambertian albedo; retroreflector as an effective gain)."""

    painted_steel: Annotated[float, doc("albedo of the tunnel's painted steel [1]", ge=0, le=1)] = 0.35
    retroreflector: Annotated[float, doc("effective gain of the markers' retroreflective tape [1]", ge=0,
                                         le=10000)] = 200.0
    board: Annotated[float, doc("albedo of the board [1]", ge=0, le=1)] = 0.6


class ManholeConfig(Section):
    """A rectangular opening in the plate, centred at (y, z) in W."""

    width_m: Annotated[float, doc("opening width along y [m]", gt=0, le=100)] = 0.40
    height_m: Annotated[float, doc("opening height along z [m]", gt=0, le=100)] = 0.60
    center_y_m: Annotated[float, doc("centre y in W [m]")] = 0.0
    center_z_m: Annotated[float, doc("centre z in W [m]")] = 1.15


class TunnelConfig(Section):
    """A box-girder tunnel: floor z = 0, ceiling z = height, walls y = +-width/2, plate at x = plate_x_m."""

    width_m: Annotated[float, doc("wall to wall [m]", gt=0, le=100)] = 0.78
    height_m: Annotated[float, doc("floor to ceiling [m]", gt=0, le=100)] = 2.30
    x_min_m: Annotated[float, doc("open end of the tunnel behind the rig, x in W [m]")] = -1.0
    plate_x_m: Annotated[float, doc("the end plate, x in W [m]")] = 2.24
    wall_thickness_m: Annotated[float, doc("thickness of walls, floor, ceiling and plate [m]", gt=0, le=10)] = 0.01
    manhole: Annotated[ManholeConfig | None, doc("an opening in the plate (none by default)")] = None

    @model_validator(mode="after")
    def _check(self) -> TunnelConfig:
        if self.x_min_m >= self.plate_x_m:
            raise ValueError(f"x_min_m {self.x_min_m} must be behind plate_x_m {self.plate_x_m}")
        return self


class BoardConfig(Section):
    """A planar board (thin box) with its centre and orientation; its front face is its local +z."""

    pose: Annotated[PoseConfig, doc("pose of the board's centre in W")]
    width_m: Annotated[float, doc("size along the board's local x [m]", gt=0, le=100)] = 1.5
    height_m: Annotated[float, doc("size along the board's local y [m]", gt=0, le=100)] = 1.0
    thickness_m: Annotated[float, doc("size along the board's local z [m]", gt=0, le=10)] = 0.01


class MeshConfig(Section):
    """Extra geometry from an STL/OBJ file (loaded with trimesh), placed at ``pose`` in W."""

    file: Annotated[Path, doc("STL or OBJ file, relative to the scenario file's folder")]
    pose: Annotated[PoseConfig, doc("pose of the mesh in W")] = PoseConfig()
    scale: Annotated[float, doc("scale applied to the mesh's coordinates (e.g. 0.001 for mm) [1]", gt=0, le=1e6)] = 1.0
    reflectivity: Annotated[float, doc("albedo (or gain) of the mesh [1]", ge=0, le=10000)] = 0.35


class BoxConfig(Section):
    """A solid box: its centre and orientation ``pose`` in W and its edge lengths along its own x, y, z axes."""

    pose: Annotated[PoseConfig, doc("pose of the box's centre in W")]
    size_x_m: Annotated[float, doc("edge length along the box's local x [m]", gt=0, le=100)]
    size_y_m: Annotated[float, doc("edge length along the box's local y [m]", gt=0, le=100)]
    size_z_m: Annotated[float, doc("edge length along the box's local z [m]", gt=0, le=100)]
    reflectivity: Annotated[float, doc("Lambertian albedo of its faces [1]", ge=0, le=1)] = 0.5


class CylinderConfig(Section):
    """A solid cylinder (a person standing, a bin, a pipe: a surface that is not a plane), its axis the local z of
    ``pose``, centred on the pose's origin."""

    pose: Annotated[PoseConfig, doc("pose of the cylinder's centre in W (its axis along the local z)")]
    radius_m: Annotated[float, doc("radius [m]", gt=0, le=100)]
    height_m: Annotated[float, doc("length along its axis, end face to end face [m]", gt=0, le=100)]
    reflectivity: Annotated[float, doc("Lambertian albedo of its surface [1]", ge=0, le=1)] = 0.5


class SphereConfig(Section):
    """A solid sphere (a ball, a globe lamp: a surface that is not a plane)."""

    center_m: Annotated[tuple[float, float, float], doc("its centre [x, y, z] in W [m]")]
    radius_m: Annotated[float, doc("radius [m]", gt=0, le=100)]
    reflectivity: Annotated[float, doc("Lambertian albedo of its surface [1]", ge=0, le=1)] = 0.5


class RoomConfig(Section):
    """A closed rectangular room (or, without ceiling, an open box) built from boxes: inner floor at z = 0, inner
    size size_x_m x size_y_m x size_z_m centred on (center_x_m, center_y_m) and turned by ``yaw`` about z;
    walls, floor and ceiling ``wall_thickness_m`` thick, outside the inner size."""

    size_x_m: Annotated[float, doc("inner size along the room's x (x_W at yaw 0) [m]", gt=0, le=100)]
    size_y_m: Annotated[float, doc("inner size along the room's y [m]", gt=0, le=100)]
    size_z_m: Annotated[float, doc("inner height, floor to ceiling [m]", gt=0, le=100)]
    center_x_m: Annotated[float, doc("x in W of the floor's centre [m]", ge=-100, le=100)] = 0.0
    center_y_m: Annotated[float, doc("y in W of the floor's centre [m]", ge=-100, le=100)] = 0.0
    yaw: Annotated[float, doc("rotation of the room about z_W [rad]", ge=-math.pi, le=math.pi)] = 0.0
    wall_thickness_m: Annotated[float, doc("thickness of walls, floor and ceiling [m]", gt=0, le=10)] = 0.05
    ceiling: Annotated[bool, doc("close the room with a ceiling (false: an open box)")] = True
    reflectivity: Annotated[float, doc("Lambertian albedo of walls, floor and ceiling [1]", ge=0, le=1)] = 0.5


class SceneConfig(Section):
    """What the laser sees: a tunnel, a room, a board, boxes, cylinders, spheres, extra meshes, the materials."""

    tunnel: Annotated[TunnelConfig | None, doc("a box-girder tunnel (none by default)")] = None
    room: Annotated[RoomConfig | None, doc("a rectangular room (none by default)")] = None
    board: Annotated[BoardConfig | None, doc("a planar marker board (none by default)")] = None
    boxes: Annotated[tuple[BoxConfig, ...], doc("solid boxes, e.g. furniture in a room")] = ()
    cylinders: Annotated[tuple[CylinderConfig, ...], doc("solid cylinders, e.g. a person-sized one (0.3 m across, "
                                                         "1.7 m tall): clutter that is not planar")] = ()
    spheres: Annotated[tuple[SphereConfig, ...], doc("solid spheres: clutter that is not planar")] = ()
    meshes: Annotated[tuple[MeshConfig, ...], doc("extra geometry")] = ()
    materials: Annotated[MaterialsConfig, doc("reflectivities")] = MaterialsConfig()
