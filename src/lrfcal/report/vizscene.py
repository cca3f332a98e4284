"""The geometry of a compiled MuJoCo model as :class:`SceneGeom` pieces posed in W, for the rerun viewer
(:mod:`lrfcal.report.viz` logs them under ``world/scene``): boxes, spheres and triangle meshes (cylinders, capsules and
ellipsoids are tessellated). mujoco is imported lazily, so ``import lrfcal`` works without it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.kinematics import homogeneous

if TYPE_CHECKING:  # pragma: no cover
    import mujoco

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class SceneGeom:
    """One piece of scene geometry, posed in W.

    kind: "box" (half_size_m = half-extents (3,)), "sphere" (radius_m) or "mesh" (vertices_m (V, 3) in the
    geom frame, faces (F, 3) vertex indices). T_W_geom (4, 4) maps geom-frame points into W.
    rgba (4,) in [0, 1].
    """

    kind: Literal["box", "sphere", "mesh"]
    name: str
    T_W_geom: FloatArray
    half_size_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    radius_m: float = 0.0
    vertices_m: FloatArray | None = None
    faces: IntArray | None = None
    is_marker: bool = False
    rgba: tuple[float, float, float, float] = (0.6, 0.6, 0.6, 1.0)


def _cylinder_mesh(radius: float, half_length: float, n: int = 24) -> tuple[FloatArray, IntArray]:
    """A closed cylinder along z: vertices (2n + 2, 3), faces (4n, 3)."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], -1)
    v = np.vstack([np.c_[ring, np.full(n, -half_length)], np.c_[ring, np.full(n, half_length)],
                   [[0, 0, -half_length], [0, 0, half_length]]])
    i = np.arange(n)
    j = (i + 1) % n
    side = np.vstack([np.c_[i, j, n + j], np.c_[i, n + j, n + i]])
    caps = np.vstack([np.c_[np.full(n, 2 * n), j, i], np.c_[np.full(n, 2 * n + 1), n + i, n + j]])
    return v, np.vstack([side, caps]).astype(np.int64)


def _ellipsoid_mesh(half_sizes: ArrayLike, n: int = 16) -> tuple[FloatArray, IntArray]:
    """A UV ellipsoid: vertices ((n + 1) * n, 3), faces (2 n^2, 3)."""
    th = np.linspace(0.0, np.pi, n + 1)
    ph = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    v = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], -1).reshape(-1, 3)
    v = v * np.asarray(half_sizes, dtype=float)
    r, c = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a = r * n + c
    b = r * n + (c + 1) % n
    a, b = a.ravel(), b.ravel()
    f = np.vstack([np.c_[a, a + n, b + n], np.c_[a, b + n, b]])
    return v, f.astype(np.int64)


def scene_geoms_from_mujoco(
    model: mujoco.MjModel,
    data: mujoco.MjData,
    geom_ids: Sequence[int] | None = None,
    *,
    skip_body_ids: Sequence[int] = (),
    geom_groups: Sequence[int] | None = None,
    is_marker: ArrayLike | None = None,
    T_W_world: ArrayLike | None = None,
    plane_half_size_m: float = 5.0,
) -> list[SceneGeom]:
    """Extract the geometry of a compiled MuJoCo model (call ``mujoco.mj_kinematics`` first).

    Args:
        model, data: the model and its data after ``mj_kinematics`` (uses geom_xpos / geom_xmat).
        geom_ids: which geoms (default all).
        skip_body_ids: bodies whose geoms are left out, with all their descendant bodies (e.g. the rig:
            ``[scene.body_M_id]`` for an lrfsim Scene).
        geom_groups: keep only geoms in these MuJoCo geom groups (default all; lrfsim: (0, 1) = the scene
            surfaces and markers the lidar sees, without the rig's visual/collision geoms).
        is_marker: (ngeom,) bool flags (e.g. ``Scene.geom_is_marker``); default: the geom's name contains
            "marker".
        T_W_world: (4, 4) transform from the model's world frame into W (default identity).
        plane_half_size_m: half-extent used for infinite planes (MuJoCo size 0).
    Returns:
        SceneGeom list: boxes (box, plane as a 1 mm thick box), spheres, and meshes (mesh, cylinder, capsule,
        ellipsoid); height fields and SDFs are skipped.
    """
    import mujoco

    ids = range(model.ngeom) if geom_ids is None else [int(g) for g in geom_ids]
    skip = {int(b) for b in skip_body_ids}
    if skip:  # close over descendants (body_parentid[b] < b for all b > 0)
        for b in range(1, model.nbody):
            if int(model.body_parentid[b]) in skip:
                skip.add(b)
    flags = None if is_marker is None else np.asarray(is_marker, dtype=bool).reshape(-1)
    T_W = np.eye(4) if T_W_world is None else np.asarray(T_W_world, dtype=float).reshape(4, 4)
    G = mujoco.mjtGeom
    out: list[SceneGeom] = []
    for g in ids:
        if int(model.geom_bodyid[g]) in skip:
            continue
        if geom_groups is not None and int(model.geom_group[g]) not in geom_groups:
            continue
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"geom{g}"
        T = T_W @ homogeneous(np.asarray(data.geom_xmat[g], dtype=float).reshape(3, 3),
                              np.asarray(data.geom_xpos[g], dtype=float))
        size = np.asarray(model.geom_size[g], dtype=float)
        mat = int(model.geom_matid[g])
        rgba = model.mat_rgba[mat] if mat >= 0 else model.geom_rgba[g]
        common: dict[str, Any] = {
            "name": name, "T_W_geom": T, "rgba": tuple(float(c) for c in rgba),
            "is_marker": bool(flags[g]) if flags is not None else ("marker" in name.lower()),
        }
        t = int(model.geom_type[g])
        if t == G.mjGEOM_BOX:
            out.append(SceneGeom("box", half_size_m=size.copy(), **common))
        elif t == G.mjGEOM_PLANE:
            hx = size[0] if size[0] > 0 else plane_half_size_m
            hy = size[1] if size[1] > 0 else plane_half_size_m
            out.append(SceneGeom("box", half_size_m=np.array([hx, hy, 0.0005]), **common))
        elif t == G.mjGEOM_SPHERE:
            r = float(size[0])
            out.append(SceneGeom("sphere", radius_m=r, half_size_m=np.full(3, r), **common))
        elif t == G.mjGEOM_MESH:
            m = int(model.geom_dataid[g])
            va, vn = int(model.mesh_vertadr[m]), int(model.mesh_vertnum[m])
            fa, fn = int(model.mesh_faceadr[m]), int(model.mesh_facenum[m])
            out.append(SceneGeom("mesh", vertices_m=np.array(model.mesh_vert[va:va + vn], dtype=float),
                                 faces=np.array(model.mesh_face[fa:fa + fn], dtype=np.int64), **common))
        elif t in (G.mjGEOM_CYLINDER, G.mjGEOM_CAPSULE):
            half = size[1] + (size[0] if t == G.mjGEOM_CAPSULE else 0.0)
            v, f = _cylinder_mesh(size[0], half)
            out.append(SceneGeom("mesh", vertices_m=v, faces=f, **common))
        elif t == G.mjGEOM_ELLIPSOID:
            v, f = _ellipsoid_mesh(size)
            out.append(SceneGeom("mesh", vertices_m=v, faces=f, **common))
    return out


__all__ = ["SceneGeom", "scene_geoms_from_mujoco"]
