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
sets, so that before and after are computed the same way (:func:`lrfcal.report.vizdata.marker_returns`). The scene
geometry comes from :mod:`lrfcal.report.vizscene`.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.io.files import atomic_file
from lrfcal.io.urdf import dh_matrix
from lrfcal.model.kinematics import transform_points
from lrfcal.report.vizdata import (
    intensity_colors,
    marker_returns,
    motor_angle_per_scan_rad,
    per_scan_rms_m,
    subsample_indices,
)
from lrfcal.report.vizscene import SceneGeom
from lrfcal.result import CalibrationResult, MarkerEvidence, PlaneEvidence

FloatArray = NDArray[np.float64]

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


# --- helpers ---------------------------------------------------------------------------------------------

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


def _log_stage(rec: Any, result: CalibrationResult, ev: MarkerEvidence, which: Literal["before", "after"]
               ) -> FloatArray:
    """Log world/<which>/{cloud,returns,residuals}; return the (K,) residual norms [m]."""
    import rerun as rr

    _log_cloud(rec, result, which)
    params = result.start if which == "before" else result.solution.params
    color = _COLOR_BEFORE if which == "before" else _COLOR_AFTER
    p, to_marker, marker, _ = marker_returns(result, ev, params, calibrated=which == "after")
    ids = ev.markers.marker_ids
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


def _log_image(rec: Any, result: CalibrationResult, ev: MarkerEvidence) -> None:
    import rerun as rr

    img = np.asarray(result.recording.scans.intensities, dtype=float)
    S, N = img.shape
    k = max(1, int(np.ceil(S * N / MAX_IMAGE_PIXELS)))  # max-pool k scans per row
    if k > 1:
        pad = (-S) % k
        img = np.vstack([img, np.zeros((pad, N))]).reshape(-1, k, N).max(axis=1)
    rgb = intensity_colors(img.ravel(), cmap="inferno").reshape(img.shape[0], N, 3)
    rec.log("intensity_image", rr.Image(rgb), static=True)
    blobs = ev.detections.blobs
    if blobs:
        bb = np.array([_bbox(b) for b in blobs])
        mins = np.c_[bb[:, 0] - 0.5, bb[:, 1] / k - 0.5]
        sizes = np.c_[bb[:, 2] - bb[:, 0] + 1.0, (bb[:, 3] - bb[:, 1]) / k + 1.0]
        b2m = ev.association.blob_to_marker
        ids = ev.markers.marker_ids
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
            assert tmp is not None  # no viewer: rrd_path is given (checked above)
            rec.save(tmp, default_blueprint=blueprint)

        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        truth = None if truth_markers_W is None else np.asarray(truth_markers_W, dtype=float).reshape(-1, 3)
        _log_scene(rec, scene_geoms or [], truth)
        match result.evidence:
            case MarkerEvidence() as ev:
                _log_markers(rec, result, ev)
            case PlaneEvidence():  # the clouds in frame M and the rig, nothing of markers
                for which in ("before", "after"):
                    _log_cloud(rec, result, which)
                _log_rig(rec, result, motor_angle_per_scan_rad(result))
        rec.flush()
        rec.disconnect()


def _log_markers(rec: Any, result: CalibrationResult, ev: MarkerEvidence) -> None:
    """A marker calibration's entities: the MDS markers, before/after returns and residuals, the intensity
    image, per-scan plots and the rig."""
    import rerun as rr

    rec.log("world/markers/mds", rr.Points3D(
        ev.markers.positions_W, radii=0.012, colors=_COLOR_MDS,
        labels=list(ev.markers.marker_ids), show_labels=True,
    ), static=True)
    norms = {w: _log_stage(rec, result, ev, w) for w in ("before", "after")}

    S = int(result.recording.scans.stamps_s.size)
    _, _, _, scan = marker_returns(result, ev, result.start)
    rms = np.stack([per_scan_rms_m(scan, norms[w], S) for w in ("before", "after")], -1)
    lam = motor_angle_per_scan_rad(result)
    _log_image(rec, result, ev)
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


__all__ = ["MAX_CLOUD_POINTS", "MAX_RIG_STEPS", "build_blueprint", "log_calibration"]
