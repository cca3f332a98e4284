"""The scene's solids and markers in W, from the scenario alone (no MuJoCo; :mod:`lrfsim.world.scene` compiles them).

The box geoms of the tunnel, the room, the board and ``scene.boxes`` (:func:`scene_boxes`), the nearest box face of
a point (:func:`nearest_box_face`), the meshes of ``scene.meshes`` placed in W (:func:`load_mesh`) and the marker
sphere centres of each layout (:func:`marker_centres_W`). Frames: W is the simulator world (lrfsim.scenario.file); a
room's frame R has its origin at the centre of the inner floor (:func:`room_pose_W`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.model.kinematics import homogeneous, rot_z, transform_points
from lrfsim.scenario.file import Scenario
from lrfsim.scenario.scene_sections import BoardConfig, MeshConfig, RoomConfig, TunnelConfig
from lrfsim.scenario.sections import BoardLayout, PointsLayout, VLayout

FloatArray = NDArray[np.float64]

_RGBA_STEEL = (0.55, 0.6, 0.62, 0.35)
_RGBA_BOARD = (0.85, 0.85, 0.8, 1.0)
_RGBA_ROOM = (0.8, 0.78, 0.72, 0.3)
_RGBA_BOX = (0.7, 0.55, 0.35, 1.0)


@dataclass(frozen=True, eq=False)
class SceneBox:
    """One box geom of the scene: its name, the pose T_W_B (4, 4) of its centre, half sizes (3,) along its own
    axes [m], Lambertian albedo [1] and display colour (4,)."""

    name: str
    T_W_B: FloatArray
    half_m: FloatArray
    reflectivity: float
    rgba: tuple[float, ...]


# --- marker layouts ---------------------------------------------------------------------------------------

def marker_centres_W(scenario: Scenario) -> FloatArray:
    """The marker sphere centres in W of the scenario's layout, shape (n, 3), in marker-id order ((0, 3) for a
    marker-less scenario)."""
    if scenario.markers is None:
        return np.zeros((0, 3))
    layout = scenario.markers.layout
    r = scenario.markers.radius_m
    if isinstance(layout, VLayout):
        assert scenario.scene.tunnel is not None  # guaranteed by Scenario's validator
        return _v_markers(layout, scenario.scene.tunnel, r, scenario.seed)
    if isinstance(layout, BoardLayout):
        assert scenario.scene.board is not None
        return board_markers(layout, scenario.scene.board, r, scenario.seed)
    assert isinstance(layout, PointsLayout)
    return np.array(layout.positions, dtype=float).reshape(-1, 3)


def _v_markers(layout: VLayout, tunnel: TunnelConfig, radius_m: float, seed: int) -> FloatArray:
    """Per wall: arm 1 from (x_start, z_top) down to the apex, arm 2 from the apex up to (x_end, z_top).

    ``per_arm`` markers per arm, the apex shared: 2 per_arm - 1 per wall (1 if per_arm == 1: the apex); each
    moved along the wall and in height by up to ``jitter_m`` (:func:`_jitter`).
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
    centres = np.vstack(out)
    centres[:, [0, 2]] += _jitter(len(centres), layout.jitter_m, seed)
    return centres


def _jitter(n: int, jitter_m: float, seed: int) -> FloatArray:
    """(n, 2) offsets uniform in +-jitter_m, from the scenario's seed in a stream of their own ("mark"),
    independent of the sensor noise (zeros without jitter)."""
    if jitter_m <= 0:
        return np.zeros((n, 2))
    return np.random.default_rng([seed, 0x6D61726B]).uniform(-jitter_m, jitter_m, size=(n, 2))


def board_markers(layout: BoardLayout, board: BoardConfig, radius_m: float, seed: int) -> FloatArray:
    """A rows x cols grid centred on the board's front face (local z = +thickness/2), one radius in front."""
    u = (np.arange(layout.cols) - (layout.cols - 1) / 2) * layout.spacing_m
    v = ((layout.rows - 1) / 2 - np.arange(layout.rows)) * layout.spacing_m  # row 0 at the top (+y local)
    uu, vv = np.meshgrid(u, v)
    local = np.column_stack([uu.ravel(), vv.ravel(), np.full(uu.size, board.thickness_m / 2 + radius_m)])
    local[:, :2] += _jitter(len(local), layout.jitter_m, seed)
    return transform_points(board.pose.to_pose().matrix(), local)


# --- boxes and meshes -------------------------------------------------------------------------------------

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


def load_mesh(cfg: MeshConfig, where: str) -> tuple[FloatArray, NDArray[np.int64]]:
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


__all__ = ["SceneBox", "board_markers", "load_mesh", "marker_centres_W", "nearest_box_face", "room_pose_W",
           "scene_boxes"]
