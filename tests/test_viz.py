"""lrfcal.report.viz (rerun .rrd, with lrfcal.report.vizdata and lrfcal.report.vizscene) and lrfcal.report.figures
(PNG) on a small synthetic
CalibrationResult.

The .rrd is read back with rerun's own reader (``rerun.chunk.RrdReader`` in rerun-sdk 0.41): every chunk's
entity path, static flag, timelines and Arrow columns are checked, not only that a file exists.
"""

from __future__ import annotations

import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pytest
from synthetic import make_result, marker_positions_W

from lrfcal.model.kinematics import points_W, pose_matrix
from lrfcal.report import viz, vizdata, vizscene
from lrfcal.report.figures import DPI, HEIGHT_PX, WIDTH_PX, write_figures

rr = pytest.importorskip("rerun")


@pytest.fixture(scope="module")
def result():
    return make_result()


def read_rrd(path: Path) -> dict[str, list[Any]]:
    """Entity path (without leading '/') -> the recording's chunks of that entity, in file order."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    assert len(reader.recordings()) == 1
    out: dict[str, list[Any]] = defaultdict(list)
    for chunk in reader.stream():
        out[chunk.entity_path.lstrip("/")].append(chunk)
    return out


def rows(chunks: list[Any], column: str, *, static: bool | None = None) -> list[np.ndarray]:
    """All non-null rows of ``column`` (e.g. "Points3D:positions") over the chunks, each as a numpy array."""
    out = []
    for c in chunks:
        if static is not None and c.is_static != static:
            continue
        rb = c.to_record_batch()
        if column not in rb.schema.names:
            continue
        for cell in rb.column(column):
            if not cell.is_valid:
                continue
            values = cell.values
            if pa.types.is_struct(values.type):  # e.g. RotationAxisAngle: one entry per instance
                out.append(np.arange(len(values)))
                continue
            while pa.types.is_list(values.type) or pa.types.is_fixed_size_list(values.type):
                values = values.flatten()
            out.append(np.asarray(values.to_numpy(zero_copy_only=False)))
    return out


def n_instances(chunks: list[Any], column: str) -> int:
    """Number of instances in the single (static) row of ``column``."""
    (row,) = rows(chunks, column)
    width = 3 if column.endswith(("positions", "vectors", "origins", "half_sizes", "centers")) else 1
    if column.startswith(("Boxes2D", "Points2D")):
        width = 2
    return row.size // width


def scene_geoms() -> list[vizscene.SceneGeom]:
    T = np.eye(4)
    return [
        vizscene.SceneGeom("box", "floor", T, half_size_m=np.array([3.0, 1.0, 0.01])),
        vizscene.SceneGeom("sphere", "marker_m00", pose_matrix(2.5, -0.4, 1.0, 0, 0, 0), radius_m=0.005,
                      is_marker=True),
        vizscene.SceneGeom("mesh", "tri", T, vertices_m=np.eye(3), faces=np.array([[0, 1, 2]])),
    ]


def test_rrd_read_back_has_the_entities_and_counts(result, tmp_path):
    path = tmp_path / "out" / "calib.rrd"
    viz.log_calibration(result, rrd_path=path, scene_geoms=scene_geoms(),
                        truth_markers_W=marker_positions_W())
    assert path.is_file()
    assert sorted(p.name for p in path.parent.iterdir()) == ["calib.rrd"]  # no temporary file left
    e = read_rrd(path)

    obs = result.evidence.observations
    K = int(np.sum(obs.marker >= 0))
    Q = result.cloud_after_M.shape[0]
    S = result.recording.scans.stamps_s.size
    B = len(result.evidence.detections.blobs)
    n = len(result.evidence.markers.marker_ids)
    assert K > 10 and B > 3 and Q > 1000

    for which in ("before", "after"):
        assert n_instances(e[f"world/{which}/cloud"], "Points3D:positions") == Q
        assert n_instances(e[f"world/{which}/cloud"], "Points3D:colors") == Q
        assert n_instances(e[f"world/{which}/returns"], "Points3D:positions") == K
        assert n_instances(e[f"world/{which}/residuals"], "Arrows3D:vectors") == K
        assert n_instances(e[f"world/{which}/residuals"], "Arrows3D:origins") == K
    assert n_instances(e["world/markers/mds"], "Points3D:positions") == n
    assert n_instances(e["world/scene/markers"], "Points3D:positions") == len(marker_positions_W())
    assert n_instances(e["world/scene/boxes"], "Boxes3D:half_sizes") == 1
    assert n_instances(e["world/scene/marker_geoms"], "Ellipsoids3D:half_sizes") == 1
    assert "world/scene/meshes/tri" in e
    assert rows(e["world"], "ViewCoordinates:xyz", static=True)

    # the after returns are the observations reprojected with the calibrated parameters, in W
    sel = obs.marker >= 0
    expect = points_W(obs.ranges_m[sel], obs.lambda_rad[sel], obs.mu_rad[sel], result.solution.params)
    (got,) = rows(e["world/after/returns"], "Points3D:positions")
    np.testing.assert_allclose(got.reshape(-1, 3), expect, atol=1e-5)
    # the after cloud is cloud_after_M moved by T_W_M (calibrated)
    (cloud,) = rows(e["world/after/cloud"], "Points3D:positions")
    T = result.solution.params.mount.matrix()
    np.testing.assert_allclose(cloud.reshape(-1, 3), result.cloud_after_M @ T[:3, :3].T + T[:3, 3], atol=1e-5)

    # intensity image with one box and one peak per blob
    (buf,) = rows(e["intensity_image"], "Image:buffer")
    assert buf.size == S * result.recording.scans.mu_rad.shape[1] * 3
    assert n_instances(e["intensity_image/blobs"], "Boxes2D:half_sizes") == B
    assert n_instances(e["intensity_image/peaks"], "Points2D:positions") == B

    # transforms: M static (calibrated mount), M' on the scan timeline, L static
    (t_M,) = rows(e["world/M"], "Transform3D:translation", static=True)
    np.testing.assert_allclose(t_M, T[:3, 3], atol=1e-6)
    assert rows(e["world/M"], "Transform3D:relation", static=True)
    assert rows(e["world/M/M_prime/L"], "Transform3D:mat3x3", static=True)
    mp = [c for c in e["world/M/M_prime"] if not c.is_static]
    assert all("scan" in c.timeline_names for c in mp)
    assert len(rows(mp, "Transform3D:rotation_axis_angle")) == S  # S <= MAX_RIG_STEPS

    # plots on the scan timeline: one motor angle per scan, [before, after] RMS per scan with returns
    assert len(rows(e["plots/motor_angle_deg"], "Scalars:scalars", static=False)) == S
    rms = rows(e["plots/residual_rms_mm"], "Scalars:scalars", static=False)
    assert len(rms) == np.unique(obs.scan[sel]).size
    rms = np.stack(rms)
    assert rms.shape[1] == 2 and np.all(rms[:, 1] < rms[:, 0])  # after better than before, per scan

    from rerun.chunk import RrdReader

    assert len(RrdReader(path).blueprints()) == 1


def test_subsampling_limits(result, tmp_path, monkeypatch):
    monkeypatch.setattr(viz, "MAX_CLOUD_POINTS", 1000)
    monkeypatch.setattr(viz, "MAX_RIG_STEPS", 20)
    path = tmp_path / "small.rrd"
    viz.log_calibration(result, rrd_path=path)
    e = read_rrd(path)
    assert n_instances(e["world/before/cloud"], "Points3D:positions") == 1000
    mp = [c for c in e["world/M/M_prime"] if not c.is_static]
    assert len(rows(mp, "Transform3D:rotation_axis_angle")) == 20
    assert len(rows(e["world/M/M_prime/L/scan"], "Points3D:positions")) == 20


def test_logged_frame_chain_reproduces_the_cloud(result, tmp_path):
    """Compose the logged T_W_M, Rz(lambda) (per scan) and T_M'_L and map the logged scan (in L) into W."""
    path = tmp_path / "chain.rrd"
    viz.log_calibration(result, rrd_path=path)
    e = read_rrd(path)

    def static_T(entity: str) -> np.ndarray:
        (t,) = rows(e[entity], "Transform3D:translation", static=True)
        (R,) = rows(e[entity], "Transform3D:mat3x3", static=True)
        (rel,) = [c.to_record_batch().column("Transform3D:relation")[0].values[0].as_py() for c in e[entity]
                  if c.is_static and "Transform3D:relation" in c.to_record_batch().schema.names]
        assert rel == rr.TransformRelation.ParentFromChild.value
        T = np.eye(4)
        T[:3, :3] = R.reshape(3, 3).T  # rerun's Mat3x3 is stored column-major
        T[:3, 3] = t
        return T

    T_W_M, T_Mp_L = static_T("world/M"), static_T("world/M/M_prime/L")
    (mp,) = [c for c in e["world/M/M_prime"] if not c.is_static]
    angles = [cell.values[0]["angle"].as_py() for cell in mp.to_record_batch().column(
        "Transform3D:rotation_axis_angle")]
    axes_ = [cell.values[0]["axis"].as_py() for cell in mp.to_record_batch().column(
        "Transform3D:rotation_axis_angle")]
    np.testing.assert_allclose(np.array(axes_), np.tile([0.0, 0.0, 1.0], (len(axes_), 1)))
    scans = rows(e["world/M/M_prime/L/scan"], "Points3D:positions")
    sc = result.recording.scans
    i = 40  # one scan: no scan subsampling at this size, so row i is scan i
    lam = float(angles[i])
    c, s = np.cos(lam), np.sin(lam)
    Rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    p_L = scans[i].reshape(-1, 3)
    p_W = p_L @ (T_W_M @ Rz @ T_Mp_L)[:3, :3].T + (T_W_M @ Rz @ T_Mp_L)[:3, 3]
    ok = np.isfinite(sc.ranges_m[i])
    expect = points_W(sc.ranges_m[i][ok], np.full(ok.sum(), lam), sc.mu_rad[i][ok], result.solution.params)
    np.testing.assert_allclose(p_W, expect, atol=1e-4)
    np.testing.assert_allclose(lam, vizdata.motor_angle_per_scan_rad(result)[i], atol=1e-6)


def test_failed_logging_leaves_no_file(result, tmp_path, monkeypatch):
    def boom(*_: Any) -> None:
        raise RuntimeError("boom")

    monkeypatch.setattr(viz, "_log_image", boom)
    with pytest.raises(RuntimeError):
        viz.log_calibration(result, rrd_path=tmp_path / "x.rrd")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError):
        viz.log_calibration(result)


MJCF = """
<mujoco>
  <asset><mesh name="tet" vertex="0 0 0  1 0 0  0 1 0  0 0 1"/></asset>
  <worldbody>
    <geom name="floor" type="plane" size="0 0 1"/>
    <geom name="wall" type="box" size="0.1 2 1" pos="3 0 1"/>
    <geom name="marker_a" type="sphere" size="0.005" pos="2.9 0 1" group="1"/>
    <geom name="post" type="cylinder" size="0.02 0.5" pos="1 1 0.5"/>
    <geom name="tetra" type="mesh" mesh="tet" pos="1 -1 0"/>
    <body name="rig" pos="0 0 0.3">
      <geom name="rig_box" type="box" size="0.05 0.05 0.05"/>
      <body name="laser"><joint type="hinge"/><geom name="laser_box" type="box" size="0.03 0.03 0.04"/></body>
    </body>
  </worldbody>
</mujoco>
"""


def test_scene_geoms_from_mujoco():
    mujoco = pytest.importorskip("mujoco")
    m = mujoco.MjModel.from_xml_string(MJCF)
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    rig = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "rig")
    T = pose_matrix(1.0, 2.0, 3.0, 0.0, 0.0, np.pi / 2)
    geoms = vizscene.scene_geoms_from_mujoco(m, d, skip_body_ids=[rig], T_W_world=T)
    by = {g.name: g for g in geoms}
    assert set(by) == {"floor", "wall", "marker_a", "post", "tetra"}  # rig and its child body skipped
    assert by["wall"].kind == "box" and by["floor"].kind == "box" and by["post"].kind == "mesh"
    assert by["marker_a"].kind == "sphere" and by["marker_a"].is_marker and not by["wall"].is_marker
    assert by["marker_a"].radius_m == pytest.approx(0.005)
    np.testing.assert_allclose(by["wall"].T_W_geom[:3, 3], T[:3, :3] @ [3, 0, 1] + T[:3, 3], atol=1e-9)
    np.testing.assert_allclose(by["wall"].half_size_m, [0.1, 2, 1])
    assert by["tetra"].faces.shape == (4, 3) and by["tetra"].vertices_m.shape == (4, 3)
    flags = np.zeros(m.ngeom, bool)
    flags[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "post")] = True
    again = {g.name: g for g in vizscene.scene_geoms_from_mujoco(m, d, is_marker=flags)}
    assert again["post"].is_marker and not again["marker_a"].is_marker and "rig_box" in again
    only = vizscene.scene_geoms_from_mujoco(m, d, geom_groups=[1])
    assert [g.name for g in only] == ["marker_a"]


def test_figures_written_at_size(result, tmp_path):
    import matplotlib.image as mpimg

    figs = write_figures(result, tmp_path / "fig")
    assert figs.skipped == {}
    paths = figs.written
    assert set(paths) == {"intensity", "alignment", "residuals"}
    for p in paths.values():
        assert p.suffix == ".png" and p.is_file()
        img = mpimg.imread(p)
        assert img.shape[:2] == (HEIGHT_PX, WIDTH_PX)
        assert float(img[..., :3].std()) > 0.05  # not blank
    assert sorted(p.name for p in (tmp_path / "fig").iterdir()) == ["alignment.png", "intensity.png",
                                                                     "residuals.png"]
    assert DPI == 150


def test_drawn_part_draws_the_same_pngs_from_a_fraction_of_the_bytes(result, tmp_path):
    """What the drawing child is sent (lrfcal.report.figures.drawn_part: the label image as an int8 candidate
    mask, no surface returns) draws the very same PNG bytes as the whole result, from far fewer pickled bytes."""
    import pickle

    from lrfcal.report.figures import drawn_detections, drawn_part

    part = drawn_part(result)
    ev, part_ev = result.evidence, part.evidence
    assert part_ev.detections.labels.dtype == np.int8
    assert np.array_equal(part_ev.detections.labels >= 0, np.asarray(ev.detections.labels) >= 0)
    assert part_ev.surface_returns is None
    assert drawn_detections(ev.detections).blobs == ev.detections.blobs
    whole = write_figures(result, tmp_path / "whole").written
    sent = write_figures(part, tmp_path / "sent").written
    assert set(whole) == set(sent) == {"intensity", "alignment", "residuals"}
    for name in whole:
        assert whole[name].read_bytes() == sent[name].read_bytes(), name
    labels_bytes = np.asarray(ev.detections.labels).nbytes
    saved = len(pickle.dumps(ev.detections)) - len(pickle.dumps(part_ev.detections))
    assert saved >= 0.8 * labels_bytes, (saved, labels_bytes)


def test_a_figure_that_cannot_be_drawn_is_skipped_with_its_reason(result, tmp_path, monkeypatch):
    import lrfcal.report.figures as figures

    def broken(*_a: object, **_k: object) -> Path:
        raise IndexError("Inconsistent shape between the condition and the input")

    monkeypatch.setattr(figures, "intensity_figure", broken)
    figs = figures.write_figures(result, tmp_path / "fig")
    assert set(figs.written) == {"alignment", "residuals"}
    assert figs.skipped == {"intensity": "IndexError: Inconsistent shape between the condition and the input"}
    assert sorted(p.name for p in (tmp_path / "fig").iterdir()) == ["alignment.png", "residuals.png"]


def test_import_does_not_pull_rerun_or_matplotlib():
    code = ("import sys, lrfcal.report.viz, lrfcal.report.vizdata, lrfcal.report.vizscene, lrfcal.report.figures; "
            "bad = [m for m in ('rerun', 'matplotlib') if m in sys.modules]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_spawn_failure_warns_and_still_saves(result, tmp_path, monkeypatch):
    import rerun as rr

    def no_viewer(**_kw):
        raise RuntimeError("Failed to spawn the viewer:\n no display")

    monkeypatch.setattr(rr, "spawn", no_viewer)
    said: list[str] = []
    path = tmp_path / "x.rrd"
    viz.log_calibration(result, rrd_path=path, spawn=True, warn=said.append)
    assert path.stat().st_size > 0
    assert len(said) == 1 and "\n" not in said[0] and "did not start" in said[0] and str(path) in said[0]
    said.clear()
    viz.log_calibration(result, spawn=True, warn=said.append)  # nothing to save: just the warning
    assert len(said) == 1


def test_intensity_image_max_pooling_keeps_a_one_cell_blob_and_pads_the_edges():
    from lrfcal.report.figintensity import _max_pool

    img = np.zeros((7, 5))
    img[6, 4] = 9.0  # in the last, padded block both ways
    img[1, 1] = 3.0
    pooled = _max_pool(img, 3, 2)
    assert pooled.shape == (3, 3)
    assert pooled[2, 2] == 9.0 and pooled[0, 0] == 3.0 and pooled.sum() == 12.0
    cand = _max_pool(img > 5.0, 3, 2)
    assert cand.dtype == bool and np.argwhere(cand).tolist() == [[2, 2]]
    assert _max_pool(img, 1, 1) is img


def test_alignment_figure_has_a_titled_panel_per_marker_and_only_returns_inside_their_panel(result, tmp_path,
                                                                                            monkeypatch):
    import re

    import lrfcal.report.figures as figures

    drawn: list[Any] = []
    monkeypatch.setattr(figures, "save", lambda fig, path: drawn.append(fig) or Path(path))
    figures.alignment_figure(result, result.evidence, tmp_path / "a.png")
    (ax,) = drawn[0].axes
    titles = [t.get_text() for t in ax.texts if re.fullmatch(r"\S+: [\d.]+ -> [\d.]+ mm", t.get_text())]
    _, _, mk, _ = vizdata.marker_returns(result, result.evidence, result.solution.params, calibrated=True)
    with_returns = [result.evidence.markers.marker_ids[m] for m in np.unique(mk)][: figures.MAX_MARKER_PANELS]
    assert sorted(t.split(":")[0] for t in titles) == sorted(with_returns)
    # every return drawn lies inside one panel's square (the frames: a LineCollection of closed squares)
    from matplotlib.collections import LineCollection, PathCollection

    lines = [c for c in ax.collections if isinstance(c, LineCollection)]
    frames = [np.asarray(seg) for seg in lines[-1].get_segments()]
    assert len(frames) == len(with_returns) and all(f.shape == (5, 2) for f in frames)
    points = np.vstack([c.get_offsets() for c in ax.collections if isinstance(c, PathCollection)])
    assert points.shape[0] > 0
    inside = np.zeros(points.shape[0], bool)
    for sq in frames:
        lo, hi = sq.min(axis=0), sq.max(axis=0)
        inside |= ((points >= lo) & (points <= hi)).all(axis=1)
    assert inside.all()
