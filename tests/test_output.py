"""Writers: calibration.yaml, rig.urdf, PLY clouds, report, atomic folder writes; reprojection."""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh
import yaml
from synthetic import START, TRUE, make_result

from lrfcal.commands.calibration_folder import calibration_folder, write_calibration
from lrfcal.errors import InputError
from lrfcal.io.files import MANIFEST_NAME
from lrfcal.io.ply import write_ply
from lrfcal.io.urdf import dh_matrix, urdf_snippet
from lrfcal.model.kinematics import ESTIMATE_NAMES, PARAM_NAMES, chain_T_M_L, points_W, pose_matrix, rot_z
from lrfcal.report.markdown import render_report
from lrfcal.stages.reproject import reproject_cloud
from lrfcal.types import TunnelGeometry


@pytest.fixture(scope="module")
def result():
    return make_result(n_scans=40, n_beams=121)


def test_dh_matrix_matches_chain():
    T = dh_matrix(TRUE.dh)
    np.testing.assert_allclose(T, chain_T_M_L(0.0, 0.0, TRUE.dh)[0], atol=1e-12)


def test_calibration_yaml_round_trip(tmp_path, result):
    out = write_calibration(tmp_path / "cal", result)
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([MANIFEST_NAME, "calibration.yaml", "cloud_after.ply", "cloud_before.ply", "report.md",
                            "rig.urdf", "rig_joints.urdf", "rig_tf.launch.py"])
    data = yaml.safe_load((out / "calibration.yaml").read_text())
    assert set(data["dh"]) == {"a", "alpha", "b", "beta"}
    assert set(data["mount"]) == {"x", "y", "z", "roll", "pitch", "yaw"}
    sol = result.solution
    for i, n in enumerate(PARAM_NAMES):
        entry = data["dh"].get(n) or data["mount"][n]
        assert entry["value"] == pytest.approx(sol.params.vector()[i])
        if n in ESTIMATE_NAMES:
            assert entry["sigma"] == pytest.approx(sol.sigma[ESTIMATE_NAMES.index(n)])
        else:  # roll, pitch, yaw: values only; the rotation's sigma is a rotation vector's
            assert "sigma" not in entry
    for k, n in enumerate(("rx", "ry", "rz")):
        assert data["mount_rotation_sigma_rad"][n] == pytest.approx(sol.sigma[3 + k])
    assert data["covariance"]["names"] == list(ESTIMATE_NAMES)
    np.testing.assert_allclose(np.array(data["covariance"]["matrix"], dtype=float), sol.covariance)
    assert data["residual_rms_m"] == pytest.approx(sol.residual_rms_m)
    assert data["n_observations"] == sol.n_observations
    used = data["markers"]["used"]
    assert used and set(used) <= set(result.evidence.markers.marker_ids)
    assert set(data["markers"]["residual_rms_m"]) == set(result.evidence.markers.marker_ids)
    assert data["baseline"] is None
    assert data["tunnel"]["after"]["width_m"] == pytest.approx(2.0)


def test_baseline_and_missing_geometry(tmp_path, result):
    r2 = dataclasses.replace(result, evidence=dataclasses.replace(result.evidence, baseline=result.solution),
                             geometry_before=None, geometry_after=TunnelGeometry(None, None, None))
    out = write_calibration(tmp_path / "cal", r2)
    data = yaml.safe_load((out / "calibration.yaml").read_text())
    assert data["baseline"]["dh"]["a"]["value"] == pytest.approx(result.solution.params.dh.a)
    assert data["tunnel"]["before"] is None and data["tunnel"]["after"]["width_m"] is None
    assert "baseline (paper)" in (out / "report.md").read_text()


def test_urdf_joints_and_chain(tmp_path, result):
    params = result.solution.params
    root = ET.fromstring(urdf_snippet(params))
    assert root.tag == "robot"
    assert {e.get("name") for e in root.findall("link")} == {"world", "motor_base", "motor", "laser"}
    joints = {j.get("name"): j for j in root.findall("joint")}
    servo, laser = joints["servo"], joints["laser_mount"]
    assert servo.get("type") == "revolute" and laser.get("type") == "fixed"
    assert servo.find("parent").get("link") == "motor_base" and servo.find("child").get("link") == "motor"
    assert laser.find("parent").get("link") == "motor" and laser.find("child").get("link") == "laser"
    assert servo.find("axis").get("xyz") == "0 0 1"

    def origin(j):
        o = j.find("origin")
        return pose_matrix(*map(float, o.get("xyz").split()), *map(float, o.get("rpy").split()))

    # world -> servo origin -> Rz(lambda) -> laser origin -> Rz(mu) -> [r, 0, 0] equals eq. (3)
    lam, mu, r = 0.7, -1.1, 2.5
    T = origin(joints["world_to_motor_base"]) @ origin(servo)
    T[:3, :3] = T[:3, :3] @ rot_z(lam)
    T = T @ origin(laser)
    p = T[:3, :3] @ rot_z(mu) @ [r, 0, 0] + T[:3, 3]
    np.testing.assert_allclose(p, points_W(r, lam, mu, params), atol=1e-7)


def test_ply_clouds(tmp_path, result):
    out = write_calibration(tmp_path / "cal", result)
    cloud = trimesh.load(out / "cloud_after.ply", process=False)
    assert len(cloud.vertices) == len(result.cloud_after_M)
    np.testing.assert_allclose(cloud.vertices, result.cloud_after_M, atol=1e-5)
    raw = cloud.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_allclose(raw["intensity"].ravel(), result.cloud_intensity, rtol=1e-6)


def test_report_tables(result):
    md = render_report(result)
    assert "| parameter | unit | start | estimate | sigma |" in md
    assert "## Per-marker residuals" in md and "| m00 |" in md
    assert "truth" not in md
    truth = {"dh": TRUE.dh.as_dict(), "mount": TRUE.mount.as_dict(),
             "tunnel": {"width_m": 2.0, "height_m": 2.3, "plate_distance_m": 2.4}}
    md = render_report(result, truth=truth)
    assert "| truth | error |" in md
    a_row = next(line for line in md.splitlines() if line.startswith("| a |"))
    assert f"{TRUE.dh.a * 1000:.2f}" in a_row
    assert "| width (wall to wall) | 2.0000 | 2.0000 | 2.0000 | +0.0 | +0.0 |" in md


def test_report_mount_truth_aligned(result):
    # truth markers in a different (rotated, shifted) frame: the mount is re-expressed in W
    T_sim_W = pose_matrix(1.0, -2.0, 0.5, 0.1, -0.2, 0.9)
    mk_W = np.asarray(result.evidence.markers.positions_W)
    mk_sim = mk_W @ T_sim_W[:3, :3].T + T_sim_W[:3, 3]
    from lrfcal.model.kinematics import Pose

    mount_sim = Pose.from_matrix(T_sim_W @ result.solution.params.mount.matrix())
    truth = {"dh": result.solution.params.dh.as_dict(), "mount": mount_sim.as_dict(),
             "markers": {i: list(p) for i, p in zip(result.evidence.markers.marker_ids, mk_sim, strict=True)}}
    md = render_report(result, truth=truth)
    x_row = next(line for line in md.splitlines() if line.startswith("| x |"))
    assert x_row.split("|")[-2].strip() in ("0.00", "-0.00")  # error column


def test_refuses_non_empty_and_overwrites_only_its_own(tmp_path, result):
    out = tmp_path / "cal"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    # a folder we did not write is never replaced, not even with overwrite; the first message already says so
    with pytest.raises(InputError, match="not written by lrf-calib.*not even with --overwrite"):
        write_calibration(out, result)
    with pytest.raises(InputError, match="not written by lrf-calib"):
        write_calibration(out, result, overwrite=True)
    assert (out / "keep.txt").read_text() == "x"
    (out / "keep.txt").unlink()
    write_calibration(out, result, report_md="# hi\n")
    with pytest.raises(InputError, match="written by lrf-calib\\): use --overwrite"):
        write_calibration(out, result, report_md="# again\n")
    write_calibration(out, result, report_md="# again\n", overwrite=True)  # our own output: replaced
    assert (out / "report.md").read_text() == "# again\n"
    # a file the user put into our output: named, and the folder is kept
    (out / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match=r"did not write \(notes.txt\)"):
        write_calibration(out, result, overwrite=True)
    assert (out / "notes.txt").read_text() == "mine" and (out / "report.md").read_text() == "# again\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal"]
    # an existing empty folder is fine
    (tmp_path / "empty").mkdir()
    write_calibration(tmp_path / "empty", result)


def test_failure_leaves_nothing(tmp_path, result):
    fig = tmp_path / "figs" / "residuals.png"
    fig.parent.mkdir()
    with pytest.raises(InputError, match="figure 'residuals' not found"):
        write_calibration(tmp_path / "out" / "cal", result, figures={"residuals": fig})
    assert list((tmp_path / "out").iterdir()) == []
    # with overwrite, a failure keeps the old folder intact
    fig.write_bytes(b"png")
    out = write_calibration(tmp_path / "out" / "cal", result, figures={"residuals": fig})
    assert (out / "residuals.png").read_bytes() == b"png"
    with pytest.raises(InputError):
        write_calibration(out, result, figures={"x": tmp_path / "nope.png"}, overwrite=True)
    assert (out / "residuals.png").exists()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["cal"]


def test_calibration_folder_in_two_steps(tmp_path, result):
    """The data files on entry (written while the figures are drawn), report and figures by finish(); a folder left
    without them is not renamed into place."""
    with calibration_folder(tmp_path / "cal", result) as folder:
        assert (folder.tmp / "cloud_after.ply").exists() and not (tmp_path / "cal").exists()
        folder.finish("# report", {})
    assert (tmp_path / "cal" / "report.md").read_text() == "# report"
    with pytest.raises(RuntimeError, match="without finish"), calibration_folder(tmp_path / "half", result):
        pass
    assert not (tmp_path / "half").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal"]


def test_reproject_cloud_and_stride(result):
    sc = result.recording.scans
    S, N = sc.ranges_m.shape
    lam = np.repeat(np.linspace(-np.pi / 2, np.pi / 2, S)[:, None], N, axis=1)
    pts, inten = reproject_cloud(sc, lam, START.dh)
    n_valid = int(np.isfinite(sc.ranges_m).sum())
    assert pts.shape == (n_valid, 3) and inten.shape == (n_valid,)
    np.testing.assert_allclose(pts, result.cloud_before_M, atol=1e-12)
    np.testing.assert_allclose(inten, result.cloud_intensity)
    pts1, _ = reproject_cloud(sc, lam[:, 0], START.dh)  # one angle per scan broadcasts
    np.testing.assert_allclose(pts1, pts)
    pts3, i3 = reproject_cloud(sc, lam, START.dh, stride=3)
    assert len(pts3) == (n_valid + 2) // 3
    np.testing.assert_allclose(pts3, pts[::3])
    np.testing.assert_allclose(i3, inten[::3])


def test_reprojection_in_blocks_gives_the_same_bits(result, monkeypatch):
    """The clouds are made CHUNK_RETURNS returns at a time: any block size (one not dividing the cloud, with
    intrinsics that scale the motor angle, the bearing and the range) gives the same numbers to the bit."""
    import lrfcal.stages.reproject as rp

    sc = result.recording.scans
    S, N = sc.ranges_m.shape
    lam = np.repeat(np.linspace(-np.pi / 2, np.pi / 2, S)[:, None], N, axis=1)
    scaled = {"motor_scale": 1.002, "beam_scale": 0.999, "range_scale": 1.001, "range_offset": 0.003}
    whole, _ = rp.reproject_clouds(sc, lam, (START.dh, START.dh), 1, ({}, scaled))
    monkeypatch.setattr(rp, "CHUNK_RETURNS", 997)
    assert whole[0].shape[0] > 3 * 997
    blocks, _ = rp.reproject_clouds(sc, lam, (START.dh, START.dh), 1, ({}, scaled))
    assert all(np.array_equal(w, b) for w, b in zip(whole, blocks, strict=True))
    assert not np.array_equal(blocks[0], blocks[1])  # the intrinsics were applied


def test_write_ply_atomic(tmp_path):
    p = write_ply(tmp_path / "c.ply", np.random.default_rng(0).normal(size=(10, 3)), np.arange(10.0))
    assert trimesh.load(p, process=False).vertices.shape == (10, 3)
    with pytest.raises(ValueError):
        write_ply(tmp_path / "d.ply", np.zeros((10, 3)), np.arange(3.0))
    assert sorted(x.name for x in tmp_path.iterdir()) == ["c.ply"]


def test_align_truth_frame_by_id_and_mirrored_symmetric_layout():
    from lrfcal.io.truth import align_truth_frame

    # a V on both walls (mirror-symmetric about y = 0), ids left l0.. and right r0..
    zs = [1.7, 0.9, 0.5, 1.3]  # not collinear: a coplanar layout would make the mirror a rotation
    sim = {f"l{k}": [0.3 + 0.3 * k, 0.39, z] for k, z in enumerate(zs)}
    sim |= {f"r{k}": [0.3 + 0.3 * k, -0.39, z] for k, z in enumerate(zs)}
    ids = tuple(sim)
    A = np.array([sim[i] for i in ids])
    T_W_sim = pose_matrix(0.2, -1.0, 0.3, 0.4, -0.1, 1.2)
    W = A @ T_W_sim[:3, :3].T + T_W_sim[:3, 3]
    T, how = align_truth_frame(W, ids, sim)
    assert how == "by marker id"
    np.testing.assert_allclose(T, T_W_sim, atol=1e-9)
    # the map came out mirrored: W positions of l_k are where r_k would be (ids swapped across y = 0)
    swapped = {i: sim[("r" if i[0] == "l" else "l") + i[1:]] for i in ids}
    W2 = np.array([swapped[i] for i in ids]) @ T_W_sim[:3, :3].T + T_W_sim[:3, 3]
    T2, how2 = align_truth_frame(W2, ids, sim)
    assert how2.startswith("by geometry")
    np.testing.assert_allclose(T2, T_W_sim, atol=1e-9)
    # unrelated points: no alignment
    assert align_truth_frame(np.random.default_rng(0).normal(size=(8, 3)), ids, sim) is None


def test_output_modes(tmp_path, result):
    import os

    from lrfcal.io.files import current_umask

    out = write_calibration(tmp_path / "cal", result)
    assert (out.stat().st_mode & 0o777) == 0o777 & ~current_umask()
    assert ((out / "cloud_after.ply").stat().st_mode & 0o777) == 0o666 & ~current_umask()
    assert os.access(out / "calibration.yaml", os.R_OK)


def test_write_ply_is_trimesh_byte_for_byte(tmp_path):
    """The cloud files keep the bytes trimesh wrote for them (the writer no longer imports it)."""
    import trimesh

    rng = np.random.default_rng(4)
    pts, inten = rng.normal(size=(257, 3)) * 10, rng.uniform(0, 9000, 257)
    for i in (inten, None):
        mesh = trimesh.Trimesh(vertices=pts, faces=np.zeros((0, 3), dtype=np.int64), process=False, validate=False)
        mesh.vertex_attributes["intensity"] = (np.zeros(len(pts)) if i is None else i).astype(np.float32)
        expected = trimesh.exchange.ply.export_ply(mesh, encoding="binary")
        assert write_ply(tmp_path / "c.ply", pts, i).read_bytes() == expected
