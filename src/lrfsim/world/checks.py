"""The checks of a scenario's geometry before :mod:`lrfsim.world.scene` compiles it; each refusal is an InputError
naming the field, e.g. "markers.layout: marker m03 at (...) intersects the left wall".

- ``scene.tunnel.manhole``: the opening fits in the plate;
- ``markers.layout``: every marker inside the tunnel and the room, outside every box, cylinder, sphere and the board,
  on the board for a board layout, and no two markers overlapping;
- ``rig.mount``: the laser's optical centre inside the tunnel and the room and outside every box, cylinder, sphere
  and part of the stand over the whole sweep or spin (it circles the motor axis).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from functools import partial

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.model.kinematics import beam_rays_M, transform_points
from lrfsim.scenario.file import Scenario
from lrfsim.scenario.scene_sections import RoomConfig, TunnelConfig
from lrfsim.scenario.sections import BoardLayout
from lrfsim.sensors.servo import covered_angles_rad

from .geometry import room_pose_W

FloatArray = NDArray[np.float64]

_EPS_M = 1e-9  # geometric slack for "touching" (markers sit exactly one radius off a surface)


def check_geometry(scenario: Scenario, markers_W: FloatArray, marker_ids: tuple[str, ...]) -> None:
    """Refuse a scenario whose manhole, markers (centres (n, 3) in W, named ``marker_ids``) or optical centre do
    not fit its scene (module docstring), in that order.

    Raises:
        InputError: naming the field and what is wrong.
    """
    tunnel = scenario.scene.tunnel
    if tunnel is not None and tunnel.manhole is not None:
        _check_manhole(tunnel)
    _check_markers(scenario, markers_W, marker_ids)
    _check_optical_centre(scenario)


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


def _cylinder_distance(p: FloatArray, T_W_C: FloatArray, radius: float, half_height: float) -> float:
    """Distance from a point p (3,) in W to a solid cylinder (centre/orientation T_W_C, axis its local z); 0 inside."""
    q = T_W_C[:3, :3].T @ (p - T_W_C[:3, 3])
    radial = max(float(np.hypot(q[0], q[1])) - radius, 0.0)
    return float(np.hypot(radial, max(abs(float(q[2])) - half_height, 0.0)))


def _solids(scenario: Scenario) -> list[tuple[str, Callable[[FloatArray], float]]]:
    """The scene's solids as (name, distance from a point in W; 0 inside): scene.boxes, cylinders and spheres."""
    out: list[tuple[str, Callable[[FloatArray], float]]] = []
    for i, box in enumerate(scenario.scene.boxes):
        half = np.array([box.size_x_m, box.size_y_m, box.size_z_m]) / 2
        out.append((f"scene.boxes[{i}]", partial(_box_distance, T_W_B=box.pose.to_pose().matrix(), half=half)))
    for i, cyl in enumerate(scenario.scene.cylinders):
        out.append((f"scene.cylinders[{i}]", partial(_cylinder_distance, T_W_C=cyl.pose.to_pose().matrix(),
                                                     radius=cyl.radius_m, half_height=cyl.height_m / 2)))
    for i, sph in enumerate(scenario.scene.spheres):
        c, rs = np.asarray(sph.center_m, dtype=float), sph.radius_m
        out.append((f"scene.spheres[{i}]", lambda p, c=c, rs=rs: max(float(np.linalg.norm(p - c)) - rs, 0.0)))
    return out


def _box_violation(p: FloatArray, r: float, scenario: Scenario) -> str | None:
    """Which of scene.boxes, scene.cylinders and scene.spheres a sphere (centre p (3,) in W, radius r; r = 0: a
    point) enters, or None."""
    for name, distance in _solids(scenario):
        d = distance(p)
        if r == 0.0 and d == 0.0:
            return f"is inside {name}"
        if r > 0.0 and d < r - _EPS_M:
            return f"intersects {name}"
    return None


def _check_optical_centre(scenario: Scenario) -> None:
    """The optical centre must stay inside the tunnel and the room, and outside every box, cylinder, sphere and part
    of the stand, over the whole sweep or spin (it circles the motor axis; a spin of a turn or more: the whole
    circle)."""
    scene = scenario.scene
    if (scene.tunnel is None and scene.room is None and not scene.boxes and not scene.cylinders and not scene.spheres
            and not scenario.rig.stand):
        return
    lo, hi = covered_angles_rad(scenario.servo)
    lam = np.linspace(lo, min(hi, lo + 2 * np.pi), 73)
    origins_M, _ = beam_rays_M(lam, np.zeros_like(lam), scenario.rig.dh.to_dh())
    origins_W = transform_points(scenario.rig.mount.to_pose().matrix(), origins_M)
    for lam_k, p, p_M in zip(lam, origins_W, origins_M, strict=True):
        what = _enclosure_violation(p, 0.0, scenario) or _box_violation(p, 0.0, scenario)
        for i, part in enumerate(scenario.rig.stand):
            half = np.array([part.size_x_m, part.size_y_m, part.size_z_m]) / 2
            if what is None and _box_distance(p_M, part.pose.to_pose().matrix(), half) == 0.0:
                what = f"is inside rig.stand[{i}]"
        if what is not None:
            raise InputError(
                f"rig.mount: the laser's optical centre at {_fmt(p)} {what} (motor angle {lam_k:.3f} rad)"
            )


__all__ = ["check_geometry"]
