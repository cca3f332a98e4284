"""Build the ground-truth MuJoCo model of a scenario: the rig (eq. (3) body chain) and the static scene.

The rig comes from ``models/rig.xml`` (nominal design values); :func:`build_scene` overwrites the poses of the
bodies ``M`` (mount, T_W_M), ``I`` (Tx(a)), ``I_prime`` (Rx(alpha)), ``L_star`` (Tz(b)) and ``L_prime``
(Rz(beta)) with the scenario's true values, so MuJoCo's forward kinematics places the optical centre:

    T_W_L' = T_W_M  Rz(lambda) Tx(a) Rx(alpha) Tz(b) Rz(beta)     (site ``laser``; lambda: hinge ``servo``)

The scene (tunnel, room, board and box geoms, meshes, marker spheres) is static: all its geoms are on the world body, in
geom groups 0 (surfaces) and 1 (markers), the only groups the lidar sees (:data:`LIDAR_GEOMGROUP`); the rig's
geoms are in groups 2 (visual) and 3 (collision). Each geom's user data is [reflectivity, is_marker]:
reflectivity is the Lambertian albedo of a surface, the retroreflector gain of a marker and 0 for the rig.
No contacts (contype = conaffinity = 0), no gravity: the hinge is set kinematically, never simulated.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.model.kinematics import beam_rays_M, homogeneous, rot_x, rot_z, transform_points

from .scenario import (
    BoardConfig,
    BoardLayout,
    MeshConfig,
    PointsLayout,
    RoomConfig,
    Scenario,
    TunnelConfig,
    VLayout,
)

FloatArray = NDArray[np.float64]

#: The MJCF rig (nominal values); build_scene starts from it.
MODELS_DIR: Path = Path(__file__).resolve().parents[2] / "models"
RIG_XML: Path = MODELS_DIR / "rig.xml"

#: Geom groups: scene surfaces, markers (both seen by the lidar), rig visual and rig collision (not seen).
SCENE_GROUP, MARKER_GROUP, RIG_VISUAL_GROUP, RIG_COLLISION_GROUP = 0, 1, 2, 3
#: mj_ray/mj_multiRay geomgroup mask of the lidar: scene geoms only, never the rig's own geoms.
LIDAR_GEOMGROUP: NDArray[np.uint8] = np.array([1, 1, 0, 0, 0, 0], dtype=np.uint8)
#: Column of each value in the geom user data (model.geom_user).
USER_REFLECTIVITY, USER_IS_MARKER = 0, 1

_EPS_M = 1e-9  # geometric slack for "touching" (markers sit exactly one radius off a surface)
_RGBA_STEEL = (0.55, 0.6, 0.62, 0.35)
_RGBA_BOARD = (0.85, 0.85, 0.8, 1.0)
_RGBA_ROOM = (0.8, 0.78, 0.72, 0.3)
_RGBA_BOX = (0.7, 0.55, 0.35, 1.0)
_RGBA_MESH = (0.6, 0.55, 0.5, 1.0)
_RGBA_MARKER = (0.95, 0.95, 1.0, 1.0)


@dataclass(frozen=True, eq=False)
class Scene:
    """A compiled ground-truth model and what the sensor simulation and the ground truth need from it.

    ``data`` is mutable working memory: :func:`laser_pose_W` sets the hinge and runs the kinematics in it.
    """

    spec: mujoco.MjSpec  # the edited spec (``spec.to_xml()`` saves the exact model)
    model: mujoco.MjModel
    data: mujoco.MjData
    site_id: int  # site ``laser``: frame L' (optical centre, +x front beam, +z mirror axis)
    joint_id: int  # the servo hinge (the paper's lambda)
    joint_qpos_adr: int  # model.jnt_qposadr[joint_id]
    body_M_id: int  # body ``M``: its pose is T_W_M
    geom_reflectivity: FloatArray  # (ngeom,) Lambertian albedo or retroreflector gain; 0 for rig geoms
    geom_is_marker: NDArray[np.bool_]  # (ngeom,)
    lidar_geomgroup: NDArray[np.uint8]  # (6,) geom groups the lidar sees
    marker_ids: tuple[str, ...]  # ("m00", "m01", ...); () without markers
    markers_W: FloatArray  # (n, 3) sphere centres in W [m]; (0, 3) without markers
    marker_radius_m: float | None  # None without markers
    marker_geom_ids: NDArray[np.int64]  # (n,) geom id of each marker, same order as marker_ids
    tunnel_truth: dict[str, float] | None  # width_m, height_m, plate_distance_m; None without a tunnel


@dataclass(frozen=True, eq=False)
class SceneBox:
    """One box geom of the scene: its name, the pose T_W_B (4, 4) of its centre, half sizes (3,) along its own
    axes [m], Lambertian albedo [1] and display colour (4,)."""

    name: str
    T_W_B: FloatArray
    half_m: FloatArray
    reflectivity: float
    rgba: tuple[float, ...]


# --- public API -------------------------------------------------------------------------------------------

def build_scene(scenario: Scenario) -> Scene:
    """Validate the scenario's geometry and compile the ground-truth model (true DH and mount values).

    Raises:
        InputError: naming the field, e.g. "markers.layout: marker m03 at (...) intersects the left wall".
    """
    tunnel = scenario.scene.tunnel
    if tunnel is not None and tunnel.manhole is not None:
        _check_manhole(tunnel)
    markers_W = marker_centres_W(scenario)
    radius_m = scenario.marker_radius_m
    marker_ids = tuple(f"m{i:02d}" for i in range(len(markers_W)))
    _check_markers(scenario, markers_W, marker_ids)
    _check_optical_centre(scenario)
    meshes = [_load_mesh(m, f"scene.meshes[{i}]") for i, m in enumerate(scenario.scene.meshes)]

    spec = mujoco.MjSpec.from_file(str(RIG_XML))
    _set_rig(spec, scenario)
    world = spec.worldbody
    mats = scenario.scene.materials
    for box in scene_boxes(scenario):
        _add_box(world, box.name, tuple(box.half_m), box.T_W_B[:3, 3], box.T_W_B[:3, :3], box.reflectivity,
                 box.rgba)
    for i, (cfg, (verts_W, faces)) in enumerate(zip(scenario.scene.meshes, meshes, strict=True)):
        mesh = spec.add_mesh(name=f"mesh{i}_asset")
        mesh.uservert = verts_W.ravel().tolist()
        mesh.userface = faces.ravel().tolist()
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # open meshes have no volume
        geom = world.add_geom(name=f"mesh{i}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"mesh{i}_asset")
        _scene_geom(geom, cfg.reflectivity, _RGBA_MESH)
    for mid, c in zip(marker_ids, markers_W, strict=True):
        assert radius_m is not None  # markers exist
        geom = world.add_geom(name=mid, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius_m, 0, 0], pos=c)
        _scene_geom(geom, mats.retroreflector, _RGBA_MARKER, is_marker=True)

    try:
        model = spec.compile()
    except ValueError as e:  # mujoco reports compile errors as ValueError
        raise InputError(f"scene: MuJoCo cannot compile the scenario's model ({e})") from None
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)

    joint_id = model.joint(scenario.servo.joint).id
    marker_geom_ids = np.array([model.geom(mid).id for mid in marker_ids], dtype=np.int64)
    tunnel_truth = None
    if tunnel is not None:
        tunnel_truth = {
            "width_m": float(tunnel.width_m),
            "height_m": float(tunnel.height_m),
            "plate_distance_m": float(tunnel.plate_x_m - scenario.rig.mount.x),
        }
    return Scene(
        spec=spec,
        model=model,
        data=data,
        site_id=model.site("laser").id,
        joint_id=joint_id,
        joint_qpos_adr=int(model.jnt_qposadr[joint_id]),
        body_M_id=model.body("M").id,
        geom_reflectivity=np.array(model.geom_user[:, USER_REFLECTIVITY], dtype=float),
        geom_is_marker=np.array(model.geom_user[:, USER_IS_MARKER] > 0.5),
        lidar_geomgroup=LIDAR_GEOMGROUP.copy(),
        marker_ids=marker_ids,
        markers_W=markers_W,
        marker_radius_m=None if radius_m is None else float(radius_m),
        marker_geom_ids=marker_geom_ids,
        tunnel_truth=tunnel_truth,
    )


def laser_pose_W(scene: Scene, lambda_rad: float) -> FloatArray:
    """Set the hinge to ``lambda_rad``, run mj_kinematics and return the site pose T_W_L' (4, 4).

    L' is the laser frame at beam angle 0 (the paper's L with mu = 0). Mutates ``scene.data``.
    """
    scene.data.qpos[scene.joint_qpos_adr] = lambda_rad
    mujoco.mj_kinematics(scene.model, scene.data)
    T = np.eye(4)
    T[:3, :3] = scene.data.site_xmat[scene.site_id].reshape(3, 3)
    T[:3, 3] = scene.data.site_xpos[scene.site_id]
    return T


def hinge_axis_W(scene: Scene) -> tuple[FloatArray, FloatArray]:
    """The motor axis in W from MuJoCo (xanchor, xaxis) after mj_kinematics: point (3,), unit axis (3,)."""
    mujoco.mj_kinematics(scene.model, scene.data)
    point = np.array(scene.data.xanchor[scene.joint_id], dtype=float)
    axis = np.array(scene.data.xaxis[scene.joint_id], dtype=float)
    return point, axis / np.linalg.norm(axis)


def marker_centres_W(scenario: Scenario) -> FloatArray:
    """The marker sphere centres in W of the scenario's layout, shape (n, 3), in marker-id order ((0, 3) for a
    marker-less scenario)."""
    if scenario.markers is None:
        return np.zeros((0, 3))
    layout = scenario.markers.layout
    r = scenario.markers.radius_m
    if isinstance(layout, VLayout):
        assert scenario.scene.tunnel is not None  # guaranteed by Scenario's validator
        return _v_markers(layout, scenario.scene.tunnel, r)
    if isinstance(layout, BoardLayout):
        assert scenario.scene.board is not None
        return _board_markers(layout, scenario.scene.board, r, scenario.seed)
    assert isinstance(layout, PointsLayout)
    return np.array(layout.positions, dtype=float).reshape(-1, 3)


# --- marker layouts ---------------------------------------------------------------------------------------

def _v_markers(layout: VLayout, tunnel: TunnelConfig, radius_m: float) -> FloatArray:
    """Per wall: arm 1 from (x_start, z_top) down to the apex, arm 2 from the apex up to (x_end, z_top).

    ``per_arm`` markers per arm, the apex shared: 2 per_arm - 1 per wall (1 if per_arm == 1: the apex).
    """
    x_apex = 0.5 * (layout.x_start_m + layout.x_end_m)
    n = layout.per_arm
    if n == 1:
        xz = np.array([[x_apex, layout.z_apex_m]])
    else:
        x1, z1 = np.linspace(layout.x_start_m, x_apex, n), np.linspace(layout.z_top_m, layout.z_apex_m, n)
        x2, z2 = np.linspace(x_apex, layout.x_end_m, n), np.linspace(layout.z_apex_m, layout.z_top_m, n)
        arm1, arm2 = np.column_stack([x1, z1]), np.column_stack([x2, z2])
        xz = np.vstack([arm1, arm2[1:]])
    out = []
    for wall in layout.walls:
        y = tunnel.width_m / 2 - radius_m if wall == "left" else -(tunnel.width_m / 2 - radius_m)
        out.append(np.column_stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]]))
    return np.vstack(out)


def _board_markers(layout: BoardLayout, board: BoardConfig, radius_m: float, seed: int) -> FloatArray:
    """A rows x cols grid centred on the board's front face (local z = +thickness/2), one radius in front."""
    rng = np.random.default_rng([seed, 0x6D61726B])  # own stream ("mark"), independent of the sensor noise
    u = (np.arange(layout.cols) - (layout.cols - 1) / 2) * layout.spacing_m
    v = ((layout.rows - 1) / 2 - np.arange(layout.rows)) * layout.spacing_m  # row 0 at the top (+y local)
    uu, vv = np.meshgrid(u, v)
    local = np.column_stack([uu.ravel(), vv.ravel(), np.full(uu.size, board.thickness_m / 2 + radius_m)])
    if layout.jitter_m > 0:
        local[:, :2] += rng.uniform(-layout.jitter_m, layout.jitter_m, size=(len(local), 2))
    return transform_points(board.pose.to_pose().matrix(), local)


# --- validation -------------------------------------------------------------------------------------------

def _fmt(p: FloatArray) -> str:
    return "(" + ", ".join(f"{v:.4f}" for v in p) + ")"


def _check_manhole(tunnel: TunnelConfig) -> None:
    mh = tunnel.manhole
    assert mh is not None
    inside = (
        abs(mh.center_y_m) + mh.width_m / 2 < tunnel.width_m / 2
        and mh.center_z_m - mh.height_m / 2 > 0
        and mh.center_z_m + mh.height_m / 2 < tunnel.height_m
    )
    if not inside:
        raise InputError(
            f"scene.tunnel.manhole: the {mh.width_m} x {mh.height_m} m opening centred at (y, z) = "
            f"({mh.center_y_m}, {mh.center_z_m}) m does not fit in the "
            f"{tunnel.width_m} x {tunnel.height_m} m plate"
        )


def _tunnel_violation(p: FloatArray, r: float, tunnel: TunnelConfig) -> str | None:
    """Which tunnel surface a sphere (centre p, radius r) crosses, or None if it is inside the tunnel."""
    half_w = tunnel.width_m / 2
    checks = (
        (p[1] + r > half_w + _EPS_M, "intersects the left wall" if p[1] < half_w else
         "is behind the left wall"),
        (p[1] - r < -half_w - _EPS_M, "intersects the right wall" if p[1] > -half_w else
         "is behind the right wall"),
        (p[2] - r < -_EPS_M, "intersects the floor" if p[2] > 0 else "is below the floor"),
        (p[2] + r > tunnel.height_m + _EPS_M, "intersects the ceiling" if p[2] < tunnel.height_m else
         "is above the ceiling"),
        (p[0] + r > tunnel.plate_x_m + _EPS_M, "intersects the plate" if p[0] < tunnel.plate_x_m else
         "is beyond the plate"),
        (p[0] - r < tunnel.x_min_m - _EPS_M, "is outside the tunnel (behind x_min_m)"),
    )
    for bad, what in checks:
        if bad:
            return what
    return None


def _box_distance(p: FloatArray, T_W_B: FloatArray, half: FloatArray) -> float:
    """Distance from a point p (3,) in W to a box (centre/orientation T_W_B, half sizes (3,)); 0 inside."""
    q = T_W_B[:3, :3].T @ (p - T_W_B[:3, 3])
    return float(np.linalg.norm(np.maximum(np.abs(q) - half, 0.0)))


def _check_markers(scenario: Scenario, markers_W: FloatArray, ids: tuple[str, ...]) -> None:
    if scenario.markers is None:
        return
    r = scenario.markers.radius_m
    board = scenario.scene.board
    layout = scenario.markers.layout
    for mid, p in zip(ids, markers_W, strict=True):
        what = _enclosure_violation(p, r, scenario) or _box_violation(p, r, scenario)
        if what is not None:
            raise InputError(f"markers.layout: marker {mid} at {_fmt(p)} {what} (radius {r} m)")
        if board is not None:
            T_W_B = board.pose.to_pose().matrix()
            half = np.array([board.width_m, board.height_m, board.thickness_m]) / 2
            if _box_distance(p, T_W_B, half) < r - _EPS_M:
                raise InputError(
                    f"markers.layout: marker {mid} at {_fmt(p)} intersects the board (radius {r} m)"
                )
            if isinstance(layout, BoardLayout):
                q = T_W_B[:3, :3].T @ (p - T_W_B[:3, 3])
                if abs(q[0]) > half[0] or abs(q[1]) > half[1]:
                    raise InputError(
                        f"markers.layout: marker {mid} at {_fmt(p)} is off the "
                        f"{board.width_m} x {board.height_m} m board "
                        f"({layout.rows} x {layout.cols} grid, spacing {layout.spacing_m} m)"
                    )
    for i, j in itertools.combinations(range(len(markers_W)), 2):
        d = float(np.linalg.norm(markers_W[i] - markers_W[j]))
        if d < 2 * r - _EPS_M:
            raise InputError(
                f"markers.layout: markers {ids[i]} and {ids[j]} overlap "
                f"(centres {d:.4f} m apart, radius {r} m)"
            )


def _room_violation(p: FloatArray, r: float, room: RoomConfig) -> str | None:
    """Which surface of the room a sphere (centre p (3,) in W, radius r) crosses, or None if it is inside."""
    T_W_R = room_pose_W(room)
    q = T_W_R[:3, :3].T @ (p - T_W_R[:3, 3])
    half = (room.size_x_m / 2, room.size_y_m / 2)
    for k, axis in enumerate("xy"):
        for sign, side in ((1.0, "+"), (-1.0, "-")):
            if sign * q[k] + r > half[k] + _EPS_M:
                return (f"intersects the {side}{axis} wall of scene.room" if sign * q[k] < half[k] else
                        f"is outside scene.room (beyond its {side}{axis} wall)")
    if q[2] - r < -_EPS_M:
        return "intersects the floor of scene.room" if q[2] > 0 else "is below the floor of scene.room"
    if q[2] + r > room.size_z_m + _EPS_M:
        if not room.ceiling:
            return "is above the walls of scene.room (open top)"
        return ("intersects the ceiling of scene.room" if q[2] < room.size_z_m else
                "is above the ceiling of scene.room")
    return None


def _enclosure_violation(p: FloatArray, r: float, scenario: Scenario) -> str | None:
    """Which tunnel or room surface a sphere (centre p (3,) in W, radius r) crosses, or None."""
    tunnel, room = scenario.scene.tunnel, scenario.scene.room
    what = _tunnel_violation(p, r, tunnel) if tunnel is not None else None
    if what is None and room is not None:
        what = _room_violation(p, r, room)
    return what


def _box_violation(p: FloatArray, r: float, scenario: Scenario) -> str | None:
    """Which of scene.boxes a sphere (centre p (3,) in W, radius r; r = 0: a point) enters, or None."""
    for i, box in enumerate(scenario.scene.boxes):
        T = box.pose.to_pose().matrix()
        half = np.array([box.size_x_m, box.size_y_m, box.size_z_m]) / 2
        d = _box_distance(p, T, half)
        if r == 0.0 and d == 0.0:
            return f"is inside scene.boxes[{i}]"
        if r > 0.0 and d < r - _EPS_M:
            return f"intersects scene.boxes[{i}]"
    return None


def _check_optical_centre(scenario: Scenario) -> None:
    """The optical centre must stay inside the tunnel and the room, and outside every box, over the whole sweep
    (it circles the motor axis)."""
    if scenario.scene.tunnel is None and scenario.scene.room is None and not scenario.scene.boxes:
        return
    servo = scenario.servo
    lam = np.linspace(min(servo.start_rad, servo.end_rad), max(servo.start_rad, servo.end_rad), 73)
    origins_M, _ = beam_rays_M(lam, np.zeros_like(lam), scenario.rig.dh.to_dh())
    origins_W = transform_points(scenario.rig.mount.to_pose().matrix(), origins_M)
    for lam_k, p in zip(lam, origins_W, strict=True):
        what = _enclosure_violation(p, 0.0, scenario) or _box_violation(p, 0.0, scenario)
        if what is not None:
            raise InputError(
                f"rig.mount: the laser's optical centre at {_fmt(p)} {what} (motor angle {lam_k:.3f} rad)"
            )


# --- geometry ---------------------------------------------------------------------------------------------

_Box = tuple[str, tuple[float, float, float], tuple[float, float, float]]  # name, half sizes, centre


def room_pose_W(room: RoomConfig) -> FloatArray:
    """T_W_R (4, 4) of the room frame R: origin at the centre of the inner floor, z up, x and y along the walls."""
    T = np.eye(4)
    T[:3, :3] = rot_z(room.yaw)
    T[:3, 3] = (room.center_x_m, room.center_y_m, 0.0)
    return T


def _room_boxes(room: RoomConfig) -> list[_Box]:
    """The room's boxes in the room frame: inner faces at x = +-size_x/2, y = +-size_y/2, z = 0 and z = size_z;
    the walls along y cover the corners."""
    t = room.wall_thickness_m
    hx, hy, h = room.size_x_m / 2, room.size_y_m / 2, room.size_z_m
    boxes: list[_Box] = [
        ("room_floor", (hx + t, hy + t, t / 2), (0.0, 0.0, -t / 2)),
        ("room_wall_px", (t / 2, hy + t, h / 2), (hx + t / 2, 0.0, h / 2)),
        ("room_wall_nx", (t / 2, hy + t, h / 2), (-hx - t / 2, 0.0, h / 2)),
        ("room_wall_py", (hx, t / 2, h / 2), (0.0, hy + t / 2, h / 2)),
        ("room_wall_ny", (hx, t / 2, h / 2), (0.0, -hy - t / 2, h / 2)),
    ]
    if room.ceiling:
        boxes.append(("room_ceiling", (hx + t, hy + t, t / 2), (0.0, 0.0, h + t / 2)))
    return boxes


def scene_boxes(scenario: Scenario) -> list[SceneBox]:
    """Every box geom of the scene, in this order: the tunnel's (walls, floor, ceiling, plate), the room's (floor,
    walls +x, -x, +y, -y, ceiling), the board, then ``scene.boxes`` (named box0, box1, ...)."""
    scene, mats = scenario.scene, scenario.scene.materials
    out: list[SceneBox] = []

    def add(name: str, T: FloatArray, half: Any, rho: float, rgba: tuple[float, ...]) -> None:
        out.append(SceneBox(name, T, np.asarray(half, dtype=float), float(rho), rgba))

    if scene.tunnel is not None:
        for name, half, pos in _tunnel_boxes(scene.tunnel):
            add(name, homogeneous(np.eye(3), pos), half, mats.painted_steel, _RGBA_STEEL)
    if scene.room is not None:
        T_W_R = room_pose_W(scene.room)
        for name, half, pos in _room_boxes(scene.room):
            add(name, T_W_R @ homogeneous(np.eye(3), pos), half, scene.room.reflectivity, _RGBA_ROOM)
    if scene.board is not None:
        board = scene.board
        add("board", board.pose.to_pose().matrix(), (board.width_m / 2, board.height_m / 2, board.thickness_m / 2),
            mats.board, _RGBA_BOARD)
    for i, box in enumerate(scene.boxes):
        add(f"box{i}", box.pose.to_pose().matrix(), (box.size_x_m / 2, box.size_y_m / 2, box.size_z_m / 2),
            box.reflectivity, _RGBA_BOX)
    return out


def _tunnel_boxes(tunnel: TunnelConfig) -> list[_Box]:
    """The tunnel's boxes; inner surfaces at y = +-w/2, z = 0, z = h and x = plate_x_m."""
    t = tunnel.wall_thickness_m
    hw, h = tunnel.width_m / 2, tunnel.height_m
    x0, x1 = tunnel.x_min_m, tunnel.plate_x_m
    cx, hx = (x0 + x1) / 2, (x1 - x0) / 2
    yo = hw + t  # outer half width
    zlo, zhi = -t, h + t  # outer z range
    boxes = [
        ("tunnel_left", (hx, t / 2, (zhi - zlo) / 2), (cx, hw + t / 2, (zlo + zhi) / 2)),
        ("tunnel_right", (hx, t / 2, (zhi - zlo) / 2), (cx, -hw - t / 2, (zlo + zhi) / 2)),
        ("tunnel_floor", (hx, yo, t / 2), (cx, 0.0, -t / 2)),
        ("tunnel_ceiling", (hx, yo, t / 2), (cx, 0.0, h + t / 2)),
    ]
    px = x1 + t / 2
    mh = tunnel.manhole
    if mh is None:
        boxes.append(("plate", (t / 2, yo, (zhi - zlo) / 2), (px, 0.0, (zlo + zhi) / 2)))
        return boxes
    y_lo, y_hi = mh.center_y_m - mh.width_m / 2, mh.center_y_m + mh.width_m / 2
    z_lo, z_hi = mh.center_z_m - mh.height_m / 2, mh.center_z_m + mh.height_m / 2
    boxes += [
        ("plate_below", (t / 2, yo, (z_lo - zlo) / 2), (px, 0.0, (zlo + z_lo) / 2)),
        ("plate_above", (t / 2, yo, (zhi - z_hi) / 2), (px, 0.0, (z_hi + zhi) / 2)),
        ("plate_left", (t / 2, (yo - y_hi) / 2, mh.height_m / 2), (px, (y_hi + yo) / 2, mh.center_z_m)),
        ("plate_right", (t / 2, (y_lo + yo) / 2, mh.height_m / 2), (px, (y_lo - yo) / 2, mh.center_z_m)),
    ]
    return boxes


def nearest_box_face(points_W: FloatArray, boxes: list[SceneBox]) -> tuple[FloatArray, NDArray[np.int64],
                                                                          FloatArray]:
    """For points (P, 3) in W, the nearest face of the given boxes (e.g. :func:`scene_boxes`): the distance to its
    surface (P,) [m] (|signed distance| of the box, 0 on a face), the index (P,) of the box in ``boxes`` and the
    face's outward unit normal (P, 3) in W. A return of the simulated lidar on a box surface has distance ~ 0."""
    pts = np.asarray(points_W, dtype=float).reshape(-1, 3)
    best = np.full(len(pts), np.inf)
    index = np.full(len(pts), -1, dtype=np.int64)
    normal = np.full((len(pts), 3), np.nan)
    for i, box in enumerate(boxes):
        R = box.T_W_B[:3, :3]
        q = (pts - box.T_W_B[:3, 3]) @ R  # (P, 3) in the box frame
        excess = np.abs(q) - box.half_m  # > 0 outside along that axis
        outside = np.linalg.norm(np.maximum(excess, 0.0), axis=1)
        dist = np.abs(outside + np.minimum(excess.max(axis=1), 0.0))
        k = excess.argmax(axis=1)
        sign = np.sign(q[np.arange(len(pts)), k])
        closer = dist < best
        best[closer], index[closer] = dist[closer], i
        normal[closer] = R[:, k[closer]].T * np.where(sign[closer] == 0, 1.0, sign[closer])[:, None]
    return best, index, normal


def _load_mesh(cfg: MeshConfig, where: str) -> tuple[FloatArray, NDArray[np.int64]]:
    """Load an STL/OBJ with trimesh, scale it and place it at its pose: vertices in W (V, 3), faces (F, 3)."""
    import trimesh

    path = Path(cfg.file)
    if not path.is_file():
        raise InputError(f"{where}.file: no such file (got '{path}')")
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for unreadable files
        # an ImportError is trimesh reaching for an optional text decoder on bytes that are not a binary STL: the
        # file is the problem, not the machine
        why = "" if isinstance(e, ImportError) else f": {type(e).__name__}: {' '.join(str(e).split())}"
        raise InputError(f"{where}.file: '{path}' is not a mesh trimesh can read (binary or ASCII STL, OBJ, PLY, "
                         f"...){why}") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), dtype=np.int64)
    verts = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), dtype=float)
    if len(faces) == 0 or len(verts) < 3 or not np.all(np.isfinite(verts)):
        raise InputError(f"{where}.file: '{path}' holds no usable triangles")
    verts_W = transform_points(cfg.pose.to_pose().matrix(), cfg.scale * verts)
    return verts_W, faces


def _quat_wxyz(R: FloatArray) -> FloatArray:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).ravel())
    return q


def _set_body(body: Any, pos: FloatArray | tuple[float, ...], R: FloatArray) -> None:
    body.pos = np.asarray(pos, dtype=float)
    body.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT  # the MJCF may use euler/axisangle
    body.quat = _quat_wxyz(R)


def _set_rig(spec: mujoco.MjSpec, scenario: Scenario) -> None:
    """Write the true mount pose and DH values into the eq. (3) bodies of the rig."""
    dh = scenario.rig.dh
    T_W_M = scenario.rig.mount.to_pose().matrix()
    _set_body(spec.body("M"), T_W_M[:3, 3], T_W_M[:3, :3])
    _set_body(spec.body("I"), (dh.a, 0.0, 0.0), np.eye(3))
    _set_body(spec.body("I_prime"), (0.0, 0.0, 0.0), rot_x(dh.alpha))
    _set_body(spec.body("L_star"), (0.0, 0.0, dh.b), np.eye(3))
    _set_body(spec.body("L_prime"), (0.0, 0.0, 0.0), rot_z(dh.beta))
    spec.joint("servo").name = scenario.servo.joint
    # rig.xml puts the servo on +z_M, behind a laser whose front beam points along -z_M (beta ~ -pi/2). If the
    # front beam points along +z_M (beta ~ +pi/2), mirror the servo, horn and bracket to -z_M (cosmetic only:
    # the lidar never sees rig geoms).
    if np.sin(dh.beta) * np.sin(dh.alpha) > 0:
        for body_name in ("M", "M_prime"):
            for geom in spec.body(body_name).geoms:
                geom.pos = np.asarray(geom.pos, dtype=float) * np.array([1.0, 1.0, -1.0])


def _scene_geom(geom: Any, reflectivity: float, rgba: tuple[float, ...], is_marker: bool = False) -> None:
    geom.group = MARKER_GROUP if is_marker else SCENE_GROUP
    geom.contype = 0
    geom.conaffinity = 0
    geom.mass = 0.0
    geom.rgba = np.array(rgba)
    geom.userdata = [float(reflectivity), 1.0 if is_marker else 0.0]


def _add_box(world: Any, name: str, half: tuple[float, ...], pos: Any, R: FloatArray, reflectivity: float,
             rgba: tuple[float, ...]) -> None:
    geom = world.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=np.asarray(half, dtype=float),
                          pos=np.asarray(pos, dtype=float), quat=_quat_wxyz(R))
    _scene_geom(geom, reflectivity, rgba)


__all__ = [
    "LIDAR_GEOMGROUP", "MODELS_DIR", "RIG_XML", "Scene", "SceneBox", "build_scene", "hinge_axis_W", "laser_pose_W",
    "marker_centres_W", "nearest_box_face", "room_pose_W", "scene_boxes",
]
