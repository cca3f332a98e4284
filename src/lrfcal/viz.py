"""The one bridge to rerun: log a :class:`CalibrationResult` (before/after alignment) to a viewer or .rrd.

rerun is imported lazily inside the functions, so ``import lrfcal`` works without it.

Entity tree (mirrors the frame tree; every transform is logged as T_parent_child, i.e.
``relation=ParentFromChild``: it maps points expressed in the child into the parent):

    world                         W, the marker frame (RIGHT_HAND_Z_UP)
    world/scene/...               scene geometry (boxes, spheres, meshes) and the true markers
    world/markers/mds             marker positions from the tape distances (MarkerMap)
    world/before/{cloud,returns,residuals}   reprojected with the start parameters (Params ``result.start``)
    world/after/{cloud,returns,residuals}    reprojected with the calibrated parameters
    world/M                       T_W_M, the calibrated mount (static)
    world/M/M_prime               Rz(lambda), on the ``scan`` timeline (<= 500 steps)
    world/M/M_prime/L             Tx(a) Rx(alpha) Tz(b) Rz(beta) (calibrated DH; static) and the scan on it
    intensity_image               the (S, N) intensity image, log-scaled, with blob boxes and peaks
    plots/motor_angle_deg         motor angle per scan ( ``scan`` timeline)
    plots/residual_rms_mm         per-scan RMS of the marker residuals, [before, after]

Residuals shown here (arrows, RMS plots) go from each reprojected marker return to the nearest point on its
marker sphere (radius ``recording.nominal.marker_radius_m``) at the MarkerMap position, for both parameter
sets, so that before and after are computed the same way.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .io.files import atomic_file
from .io.urdf import dh_matrix
from .model.kinematics import Params, homogeneous, points_W, transform_points
from .types import CalibrationResult

if TYPE_CHECKING:  # pragma: no cover
    import mujoco

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Upper bound on the points logged per cloud (uniform subsample above it).
MAX_CLOUD_POINTS = 300_000
#: Upper bound on the motor-angle steps logged for the moving rig frames and the scan lines.
MAX_RIG_STEPS = 500
#: Upper bound on the pixels of the logged intensity image; taller images are max-pooled along the scans.
MAX_IMAGE_PIXELS = 6_000_000

_COLOR_BEFORE = (230, 120, 30)
_COLOR_AFTER = (40, 170, 80)
_COLOR_MDS = (220, 40, 200)
_COLOR_TRUTH = (250, 250, 250)


# --- scene geometry --------------------------------------------------------------------------------

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


# --- helpers (pure numpy, tested through log_calibration) --------------------------------------------------

def subsample_indices(n: int, max_n: int) -> IntArray:
    """Indices of an evenly strided subset of range(n) with at most max_n elements (all when n <= max_n)."""
    if n <= max_n:
        return np.arange(n, dtype=np.int64)
    return np.unique(np.linspace(0, n - 1, max_n).round().astype(np.int64))


def intensity_colors(intensity: ArrayLike, cmap: str = "viridis") -> NDArray[np.uint8]:
    """(Q,) intensities [counts] -> (Q, 3) uint8 RGB; log10(1 + I) scaled between its 1st and 99.5th
    percentiles."""
    import matplotlib

    x = np.log10(1.0 + np.clip(np.nan_to_num(np.asarray(intensity, dtype=float)), 0.0, None))
    if x.size == 0:
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(x, [1.0, 99.5])
    u = np.clip((x - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return (matplotlib.colormaps[cmap](u)[..., :3] * 255).astype(np.uint8)


def marker_returns(
    result: CalibrationResult, params: Params
) -> tuple[FloatArray, FloatArray, IntArray, IntArray]:
    """Marker returns reprojected with ``params`` and their residual vectors to the marker surface.

    Only observations assigned to a marker (marker >= 0) are used (K of them).
    Returns:
        points_W (K, 3) reprojected returns; to_marker_W (K, 3) vector from each return to the nearest point
        of its marker sphere (centre = MarkerMap position, radius = nominal marker radius); marker (K,);
        scan (K,).
    """
    obs = result.observations
    sel = obs.marker >= 0
    p = points_W(obs.ranges_m[sel], obs.lambda_rad[sel], obs.mu_rad[sel], params)
    centres = result.markers.positions_W[obs.marker[sel]]
    d = centres - p
    n = np.linalg.norm(d, axis=1, keepdims=True)
    r = float(result.recording.nominal.marker_radius_m)
    with np.errstate(invalid="ignore", divide="ignore"):
        to_surface = np.where(n > r, d * (1.0 - r / np.where(n > 0, n, 1.0)), 0.0)
    return p, to_surface, obs.marker[sel].astype(np.int64), obs.scan[sel].astype(np.int64)


def per_scan_rms_m(scan: IntArray, residual_norm_m: FloatArray, n_scans: int) -> FloatArray:
    """(S,) RMS of the residual norms of the returns of each scan; NaN for scans without marker returns."""
    ss = np.bincount(scan, weights=residual_norm_m**2, minlength=n_scans)
    cnt = np.bincount(scan, minlength=n_scans)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, np.sqrt(ss / np.maximum(cnt, 1)), np.nan)


def motor_angle_per_scan_rad(result: CalibrationResult) -> FloatArray:
    """(S,) motor angle at the middle of each scan: joint positions interpolated at stamp + scan_time / 2.

    Ignores any laser/servo clock offset (good enough to animate the rig); falls back to the observations'
    lambda (nearest observed scan) when there are no joint samples.
    """
    sc = result.recording.scans
    js = result.recording.joints
    t = sc.stamps_s + 0.5 * sc.scan_time_s
    if js.stamps_s.size >= 2:
        order = np.argsort(js.stamps_s)
        return np.interp(t, js.stamps_s[order], js.positions_rad[order])
    obs = result.observations
    if len(obs) == 0:
        return np.zeros(sc.stamps_s.size)
    return np.interp(np.arange(sc.stamps_s.size), obs.scan.astype(float), obs.lambda_rad)


def _bbox(blob: Any) -> tuple[float, float, float, float]:
    """Pixel bbox of a blob as (beam_min, scan_min, beam_max, scan_max), inclusive pixel indices."""
    return (float(blob.beam_idx.min()), float(blob.scan_idx.min()), float(blob.beam_idx.max()),
            float(blob.scan_idx.max()))


def _quat_xyzw(R: FloatArray) -> FloatArray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) in rerun's xyzw order."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float).reshape(-1, 3, 3)).as_quat()


def _rgba8(rgba: Sequence[float]) -> list[int]:
    return [int(round(255 * min(max(float(c), 0.0), 1.0))) for c in rgba]


# --- logging ------------------------------------------------------------------------------------------

def build_blueprint() -> Any:
    """Default layout: before | after (3D) on top; intensity image | residual and motor-angle plots below."""
    import rerun.blueprint as rrb

    common = ["+ world/scene/**", "+ world/markers/**"]
    before = rrb.Spatial3DView(origin="world", name="before (start parameters)",
                               contents=[*common, "+ world/before/**"])
    after = rrb.Spatial3DView(origin="world", name="after (calibrated)",
                              contents=[*common, "+ world/after/**", "+ world/M/**"])
    image = rrb.Spatial2DView(origin="intensity_image", name="intensity (log) and detected blobs")
    plots = rrb.Vertical(
        rrb.TimeSeriesView(origin="plots/residual_rms_mm", name="residual RMS per scan [mm]"),
        rrb.TimeSeriesView(origin="plots/motor_angle_deg", name="motor angle [deg]"),
    )
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(before, after), rrb.Horizontal(image, plots, column_shares=[2, 1]),
                     row_shares=[3, 2]),
        collapse_panels=True,
    )


def _log_scene(rec: Any, geoms: Sequence[SceneGeom], truth_markers_W: FloatArray | None) -> None:
    import rerun as rr

    boxes = [g for g in geoms if g.kind == "box"]
    spheres = [g for g in geoms if g.kind == "sphere" and not g.is_marker]
    marker_geoms = [g for g in geoms if g.kind == "sphere" and g.is_marker]
    if boxes:
        T = np.stack([g.T_W_geom for g in boxes])
        rec.log("world/scene/boxes", rr.Boxes3D(
            centers=T[:, :3, 3], half_sizes=np.stack([g.half_size_m for g in boxes]),
            quaternions=_quat_xyzw(T[:, :3, :3]), colors=[_rgba8(g.rgba) for g in boxes],
            labels=[g.name for g in boxes], show_labels=False,
            fill_mode=rr.components.FillMode.MajorWireframe,
        ), static=True)
    for path, group in (("world/scene/spheres", spheres), ("world/scene/marker_geoms", marker_geoms)):
        if group:
            T = np.stack([g.T_W_geom for g in group])
            rec.log(path, rr.Ellipsoids3D(
                centers=T[:, :3, 3], half_sizes=[[g.radius_m] * 3 for g in group],
                colors=[_rgba8(g.rgba) for g in group], labels=[g.name for g in group], show_labels=False,
                fill_mode=rr.components.FillMode.Solid,
            ), static=True)
    for g in geoms:
        if g.kind == "mesh" and g.vertices_m is not None and g.faces is not None:
            rec.log(f"world/scene/meshes/{rr.escape_entity_path_part(g.name)}", rr.Mesh3D(
                vertex_positions=transform_points(g.T_W_geom, g.vertices_m), triangle_indices=g.faces,
                albedo_factor=_rgba8(g.rgba),
            ), static=True)
    if truth_markers_W is not None and len(truth_markers_W):
        rec.log("world/scene/markers", rr.Points3D(
            np.asarray(truth_markers_W, dtype=float).reshape(-1, 3), radii=0.008, colors=_COLOR_TRUTH,
        ), static=True)


def _log_cloud(rec: Any, result: CalibrationResult, which: Literal["before", "after"]) -> None:
    """Log world/<which>/cloud: the reprojected cloud in W (intensity colours), at most MAX_CLOUD_POINTS."""
    import rerun as rr

    params = result.start if which == "before" else result.solution.params
    cloud_M = result.cloud_before_M if which == "before" else result.cloud_after_M
    cloud_M = np.asarray(cloud_M, dtype=float).reshape(-1, 3)
    inten = np.asarray(result.cloud_intensity, dtype=float).reshape(-1)
    if inten.size != cloud_M.shape[0]:
        inten = np.zeros(cloud_M.shape[0])
    ok = np.flatnonzero(np.isfinite(cloud_M).all(axis=1))
    ok = ok[subsample_indices(ok.size, MAX_CLOUD_POINTS)]
    cloud_W = transform_points(params.mount.matrix(), cloud_M[ok])
    rec.log(f"world/{which}/cloud", rr.Points3D(cloud_W, colors=intensity_colors(inten[ok]), radii=0.004),
            static=True)


def _log_stage(rec: Any, result: CalibrationResult, which: Literal["before", "after"]) -> FloatArray:
    """Log world/<which>/{cloud,returns,residuals}; return the (K,) residual norms [m]."""
    import rerun as rr

    assert result.markers is not None
    _log_cloud(rec, result, which)
    params = result.start if which == "before" else result.solution.params
    color = _COLOR_BEFORE if which == "before" else _COLOR_AFTER
    p, to_marker, marker, _ = marker_returns(result, params)
    ids = result.markers.marker_ids
    rec.log(f"world/{which}/returns", rr.Points3D(
        p, radii=0.006, colors=color, labels=[ids[m] for m in marker], show_labels=False,
    ), static=True)
    rec.log(f"world/{which}/residuals", rr.Arrows3D(origins=p, vectors=to_marker, colors=color, radii=0.0015),
            static=True)
    return np.linalg.norm(to_marker, axis=1)


def _log_rig(rec: Any, result: CalibrationResult, lam_scan: FloatArray) -> None:
    import rerun as rr

    P = rr.TransformRelation.ParentFromChild
    params = result.solution.params
    T_W_M = params.mount.matrix()
    rec.log("world/M", rr.Transform3D(translation=T_W_M[:3, 3], mat3x3=T_W_M[:3, :3], relation=P),
            rr.TransformAxes3D(0.15), static=True)
    T_Mp_L = dh_matrix(params.dh)
    rec.log("world/M/M_prime/L", rr.Transform3D(translation=T_Mp_L[:3, 3], mat3x3=T_Mp_L[:3, :3], relation=P),
            rr.TransformAxes3D(0.08), static=True)
    rec.log("world/M/M_prime", rr.TransformAxes3D(0.1), static=True)
    # the UTM-30LX housing, 60 x 60 x 87 mm (Hokuyo UTM-30LX-EW spec sheet, hokuyo-aut.jp), below the scan plane
    housing = rr.Boxes3D(centers=[[0, 0, -0.02]], half_sizes=[[0.03, 0.03, 0.0435]], colors=[(90, 90, 200)])
    rec.log("world/M/M_prime/L/housing", housing, static=True)

    sc = result.recording.scans
    S = lam_scan.size
    ranges = np.asarray(sc.ranges_m, dtype=float)
    c, s = np.cos(sc.mu_rad), np.sin(sc.mu_rad)
    for i in subsample_indices(S, MAX_RIG_STEPS):
        rec.set_time("scan", sequence=int(i))
        rec.set_time("time", duration=float(sc.stamps_s[i] - sc.stamps_s[0]))
        rec.log("world/M/M_prime", rr.Transform3D(
            rotation=rr.RotationAxisAngle(axis=[0.0, 0.0, 1.0], radians=float(lam_scan[i])), relation=P))
        r = ranges[i]
        ok = np.isfinite(r)
        rec.log("world/M/M_prime/L/scan", rr.Points3D(
            np.stack([r[ok] * c[i][ok], r[ok] * s[i][ok], np.zeros(int(ok.sum()))], -1), radii=0.006,
            colors=(240, 60, 60)))


def _log_image(rec: Any, result: CalibrationResult) -> None:
    import rerun as rr

    img = np.asarray(result.recording.scans.intensities, dtype=float)
    S, N = img.shape
    k = max(1, int(np.ceil(S * N / MAX_IMAGE_PIXELS)))  # max-pool k scans per row
    if k > 1:
        pad = (-S) % k
        img = np.vstack([img, np.zeros((pad, N))]).reshape(-1, k, N).max(axis=1)
    rgb = intensity_colors(img.ravel(), cmap="inferno").reshape(img.shape[0], N, 3)
    rec.log("intensity_image", rr.Image(rgb), static=True)
    blobs = result.detections.blobs
    if blobs:
        bb = np.array([_bbox(b) for b in blobs])
        mins = np.c_[bb[:, 0] - 0.5, bb[:, 1] / k - 0.5]
        sizes = np.c_[bb[:, 2] - bb[:, 0] + 1.0, (bb[:, 3] - bb[:, 1]) / k + 1.0]
        b2m = result.association.blob_to_marker
        ids = result.markers.marker_ids
        labels = [f"blob {j}" + (f" -> {ids[b2m[j]]}" if j < b2m.size and b2m[j] >= 0 else "")
                  for j in range(len(blobs))]
        rec.log("intensity_image/blobs", rr.Boxes2D(mins=mins, sizes=sizes, labels=labels, show_labels=False,
                                                    colors=(0, 220, 255)), static=True)
        peaks = np.array([[b.peak_beam, b.peak_scan / k] for b in blobs], dtype=float)
        rec.log("intensity_image/peaks", rr.Points2D(peaks, radii=1.0, colors=(0, 255, 0)), static=True)


def log_calibration(
    result: CalibrationResult,
    *,
    rrd_path: Path | None = None,
    spawn: bool = False,
    scene_geoms: list[SceneGeom] | None = None,
    truth_markers_W: ArrayLike | None = None,
    app_id: str = "lrfcal",
    warn: Callable[[str], None] | None = None,
) -> None:
    """Log the calibration (before/after clouds, marker returns, residuals, intensity image, rig) to rerun.

    If the viewer cannot be spawned, ``warn`` gets one line and the recording still goes to ``rrd_path``.

    Args:
        result: the pipeline's output.
        rrd_path: write an .rrd file here (headless; written to a temporary file in the same folder and
            renamed once complete, so readers never see a partial file).
        spawn: also start a viewer and stream to it.
        scene_geoms: geometry already posed in W (see :func:`scene_geoms_from_mujoco`).
        truth_markers_W: (n, 3) true marker centres in W, logged as ``world/scene/markers``.
        app_id: rerun application id.
    Raises:
        ValueError: neither rrd_path nor spawn was given.
    """
    import rerun as rr

    if rrd_path is None and not spawn:
        raise ValueError("log_calibration: give rrd_path and/or spawn=True")
    blueprint = build_blueprint()
    rec = rr.RecordingStream(app_id, recording_id=str(uuid.uuid4()))
    with ExitStack() as stack:
        tmp = None if rrd_path is None else stack.enter_context(atomic_file(rrd_path))
        if spawn:
            try:
                rr.spawn(connect=False)
            except Exception as err:  # no viewer binary, no display, port taken: go on without the viewer
                spawn = False
                if warn is not None:
                    warn(f"--spawn: the rerun viewer did not start ({' '.join(str(err).split())[:200]})"
                         + (f"; saving {rrd_path}" if rrd_path is not None else ""))
                if tmp is None:
                    return
        if spawn:
            sinks: list[Any] = [rr.GrpcSink()]
            if tmp is not None:
                sinks.append(rr.FileSink(tmp))
            rec.set_sinks(*sinks, default_blueprint=blueprint)
        else:
            rec.save(tmp, default_blueprint=blueprint)

        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        truth = None if truth_markers_W is None else np.asarray(truth_markers_W, dtype=float).reshape(-1, 3)
        _log_scene(rec, scene_geoms or [], truth)
        if result.markers is None:  # targetless: the clouds in frame M and the rig, nothing of markers
            for which in ("before", "after"):
                _log_cloud(rec, result, which)  # type: ignore[arg-type]
            _log_rig(rec, result, motor_angle_per_scan_rad(result))
        else:
            _log_markers(rec, result)
        rec.flush()
        rec.disconnect()


def _log_markers(rec: Any, result: CalibrationResult) -> None:
    """A marker calibration's entities: the MDS markers, before/after returns and residuals, the intensity
    image, per-scan plots and the rig."""
    import rerun as rr

    assert result.markers is not None
    rec.log("world/markers/mds", rr.Points3D(
        result.markers.positions_W, radii=0.012, colors=_COLOR_MDS,
        labels=list(result.markers.marker_ids), show_labels=True,
    ), static=True)
    norms = {w: _log_stage(rec, result, w) for w in ("before", "after")}  # type: ignore[arg-type]

    S = int(result.recording.scans.stamps_s.size)
    _, _, _, scan = marker_returns(result, result.start)
    rms = np.stack([per_scan_rms_m(scan, norms[w], S) for w in ("before", "after")], -1)
    lam = motor_angle_per_scan_rad(result)
    _log_image(rec, result)
    rec.log("plots/residual_rms_mm", rr.SeriesLines(names=["before", "after"],
                                                     colors=[_COLOR_BEFORE, _COLOR_AFTER]), static=True)
    rec.log("plots/motor_angle_deg", rr.SeriesLines(names=["motor angle lambda"]), static=True)
    stamps = result.recording.scans.stamps_s
    for i in range(S):
        rec.set_time("scan", sequence=i)
        rec.set_time("time", duration=float(stamps[i] - stamps[0]))
        rec.log("plots/motor_angle_deg", rr.Scalars(float(np.rad2deg(lam[i]))))
        if np.isfinite(rms[i]).all():
            rec.log("plots/residual_rms_mm", rr.Scalars(rms[i] * 1e3))
    _log_rig(rec, result, lam)


__all__ = [
    "MAX_CLOUD_POINTS", "MAX_RIG_STEPS", "SceneGeom", "build_blueprint", "intensity_colors",
    "log_calibration", "marker_returns", "motor_angle_per_scan_rad", "per_scan_rms_m",
    "scene_geoms_from_mujoco", "subsample_indices",
]
