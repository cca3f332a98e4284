"""Build the ground-truth MuJoCo model of a scenario: the rig (eq. (3) body chain) and the static scene.

The rig comes from ``models/rig.xml`` (nominal design values); :func:`build_scene` overwrites the poses of the
bodies ``M`` (mount, T_W_M), ``I`` (Tx(a)), ``I_prime`` (Rx(alpha)), ``L_star`` (Tz(b)) and ``L_prime``
(Rz(beta)) with the scenario's true values, so MuJoCo's forward kinematics places the optical centre:

    T_W_L' = T_W_M  Rz(lambda) Tx(a) Rx(alpha) Tz(b) Rz(beta)     (site ``laser``; lambda: hinge ``servo``)

The scene (tunnel, room, board, box, cylinder and sphere geoms, meshes, marker spheres) is static: all its geoms are on
the world body, in geom groups 0 (surfaces) and 1 (markers), the only groups the lidar sees
(:data:`LIDAR_GEOMGROUP`); the rig's geoms are in groups 2 (visual) and 3 (collision). The stand's parts
(``rig.stand``) are boxes on the body ``M`` (they move with the mount, not with the motor's turn), in group 0: the
lidar sees them, as a tilting scanner sees its own stand. Each geom's user data is [reflectivity, is_marker]:
reflectivity is the Lambertian albedo of a surface, the retroreflector gain of a marker and 0 for the rig.
No contacts (contype = conaffinity = 0), no gravity: the hinge is set kinematically, never simulated.

Where the solids and markers are comes from :mod:`lrfsim.world.geometry`; the scenario's geometry is checked first
by :mod:`lrfsim.world.checks`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.model.kinematics import rot_x, rot_z
from lrfsim.scenario.file import Scenario

from .checks import check_geometry
from .geometry import load_mesh, marker_centres_W, scene_boxes

FloatArray = NDArray[np.float64]

#: The MJCF rig (nominal values); build_scene starts from it.
MODELS_DIR: Path = Path(__file__).resolve().parents[3] / "models"
RIG_XML: Path = MODELS_DIR / "rig.xml"

#: Geom groups: scene surfaces, markers (both seen by the lidar), rig visual and rig collision (not seen).
SCENE_GROUP, MARKER_GROUP, RIG_VISUAL_GROUP, RIG_COLLISION_GROUP = 0, 1, 2, 3
#: mj_ray/mj_multiRay geomgroup mask of the lidar: scene geoms only, never the rig's own geoms.
LIDAR_GEOMGROUP: NDArray[np.uint8] = np.array([1, 1, 0, 0, 0, 0], dtype=np.uint8)
#: Column of each value in the geom user data (model.geom_user).
USER_REFLECTIVITY, USER_IS_MARKER = 0, 1

_RGBA_MESH = (0.6, 0.55, 0.5, 1.0)
_RGBA_MARKER = (0.95, 0.95, 1.0, 1.0)
_RGBA_CLUTTER = (0.45, 0.5, 0.7, 1.0)
_RGBA_STAND = (0.3, 0.3, 0.3, 1.0)


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


def build_scene(scenario: Scenario) -> Scene:
    """Validate the scenario's geometry and compile the ground-truth model (true DH and mount values).

    Raises:
        InputError: naming the field, e.g. "markers.layout: marker m03 at (...) intersects the left wall".
    """
    markers_W = marker_centres_W(scenario)
    radius_m = scenario.marker_radius_m
    marker_ids = tuple(f"m{i:02d}" for i in range(len(markers_W)))
    check_geometry(scenario, markers_W, marker_ids)
    meshes = [load_mesh(m, f"scene.meshes[{i}]") for i, m in enumerate(scenario.scene.meshes)]
    spec = _scene_spec(scenario, markers_W, marker_ids, meshes)
    try:
        model = spec.compile()
    except ValueError as e:  # mujoco reports compile errors as ValueError
        raise InputError(f"scene: MuJoCo cannot compile the scenario's model ({e})") from None
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)

    joint_id = model.joint(scenario.servo.joint).id
    marker_geom_ids = np.array([model.geom(mid).id for mid in marker_ids], dtype=np.int64)
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
        tunnel_truth=_tunnel_truth(scenario),
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


def _scene_spec(scenario: Scenario, markers_W: FloatArray, marker_ids: tuple[str, ...],
                meshes: list[tuple[FloatArray, NDArray[np.int64]]]) -> mujoco.MjSpec:
    """The rig of ``models/rig.xml`` with the true values and the stand's parts on its body M, and on the world body
    the scene's boxes, cylinders, spheres, meshes (vertices in W, faces) and marker spheres (centres (n, 3) in W)."""
    radius_m = scenario.marker_radius_m
    spec = mujoco.MjSpec.from_file(str(RIG_XML))
    _set_rig(spec, scenario)
    world = spec.worldbody
    mats = scenario.scene.materials
    for box in scene_boxes(scenario):
        _add_box(world, box.name, tuple(box.half_m), box.T_W_B[:3, 3], box.T_W_B[:3, :3], box.reflectivity,
                 box.rgba)
    for i, cyl in enumerate(scenario.scene.cylinders):
        T = cyl.pose.to_pose().matrix()
        geom = world.add_geom(name=f"cylinder{i}", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                              size=[cyl.radius_m, cyl.height_m / 2, 0.0], pos=T[:3, 3], quat=_quat_wxyz(T[:3, :3]))
        _scene_geom(geom, cyl.reflectivity, _RGBA_CLUTTER)
    for i, sph in enumerate(scenario.scene.spheres):
        geom = world.add_geom(name=f"sphere{i}", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[sph.radius_m, 0.0, 0.0],
                              pos=np.asarray(sph.center_m, dtype=float))
        _scene_geom(geom, sph.reflectivity, _RGBA_CLUTTER)
    body_M = spec.body("M")
    for i, part in enumerate(scenario.rig.stand):  # in frame M, after _set_rig (which mirrors the rig's own geoms)
        T = part.pose.to_pose().matrix()
        _add_box(body_M, f"stand{i}", (part.size_x_m / 2, part.size_y_m / 2, part.size_z_m / 2), T[:3, 3],
                 T[:3, :3], part.reflectivity, _RGBA_STAND)
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
    return spec


def _tunnel_truth(scenario: Scenario) -> dict[str, float] | None:
    """The tunnel's width, height and plate distance from the mount [m]; None without a tunnel."""
    tunnel = scenario.scene.tunnel
    if tunnel is None:
        return None
    return {
        "width_m": float(tunnel.width_m),
        "height_m": float(tunnel.height_m),
        "plate_distance_m": float(tunnel.plate_x_m - scenario.rig.mount.x),
    }


# --- MuJoCo spec editing ----------------------------------------------------------------------------------

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


def _add_box(body: Any, name: str, half: tuple[float, ...], pos: Any, R: FloatArray, reflectivity: float,
             rgba: tuple[float, ...]) -> None:
    geom = body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=np.asarray(half, dtype=float),
                         pos=np.asarray(pos, dtype=float), quat=_quat_wxyz(R))
    _scene_geom(geom, reflectivity, rgba)


__all__ = [
    "LIDAR_GEOMGROUP", "MODELS_DIR", "RIG_XML", "Scene", "build_scene", "hinge_axis_W", "laser_pose_W",
]
