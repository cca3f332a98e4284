"""The MuJoCo rig and scene: eq. (3) forward kinematics, models compile cleanly, validation, ray casts."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pytest
import yaml

from lrfcal.errors import InputError
from lrfcal.model.kinematics import DH, Pose, chain_T_M_L
from lrfsim.scenario.file import load_scenario, parse_scenario
from lrfsim.world.scene import MODELS_DIR, build_scene, hinge_axis_W, laser_pose_W

REPO = Path(__file__).resolve().parents[1]
SCENARIOS = sorted((REPO / "scenarios").glob("*.yaml"))
MODELS = sorted(MODELS_DIR.glob("*.xml"))


def _tunnel_dict() -> dict[str, Any]:
    return yaml.safe_load((REPO / "scenarios" / "tunnel_v.yaml").read_text())


def _points_dict(positions: list[list[float]], **scene: Any) -> dict[str, Any]:
    """A minimal scenario: the tunnel_v rig, no tunnel, markers at explicit positions."""
    d = _tunnel_dict()
    d["scene"] = {"tunnel": None, **scene}
    d["markers"] = {"radius_m": 0.005, "layout": {"kind": "points", "positions": positions}}
    return d


def _fibonacci_sphere(n: int) -> np.ndarray:
    """n roughly uniform unit vectors, shape (n, 3)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5**0.5) * i
    r = np.sqrt(1 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _ray(scene: Any, pnt: np.ndarray, vec: np.ndarray, geomgroup: Any = "lidar") -> tuple[float, int]:
    """Distance [m] along ``vec`` normalised (mj_ray measures in units of |vec|) and the hit geom id."""
    gid = np.array([-1], dtype=np.int32)
    group = scene.lidar_geomgroup if isinstance(geomgroup, str) else geomgroup
    unit = np.asarray(vec, float) / np.linalg.norm(vec)
    d = mujoco.mj_ray(scene.model, scene.data, np.asarray(pnt, float), unit, group, 1, -1, gid)
    return d, int(gid[0])


# --- (a) MuJoCo's body chain = eq. (3) --------------------------------------------------------------------

def test_site_pose_matches_eq3_chain() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        dh = DH(rng.uniform(-0.05, 0.05), rng.uniform(-math.pi, math.pi), rng.uniform(-0.05, 0.05),
                rng.uniform(-math.pi, math.pi))
        mount = Pose(*rng.uniform(-2, 2, 3), *rng.uniform(-math.pi, math.pi, 3))
        d = _points_dict([[5.0, 5.0, 5.0]])
        d["rig"]["dh"] = dh.as_dict()
        d["rig"]["mount"] = mount.as_dict()
        scene = build_scene(parse_scenario(d, "random"))
        T_W_M = mount.matrix()
        for lam in rng.uniform(-2 * math.pi, 2 * math.pi, 3):
            expected = T_W_M @ chain_T_M_L(lam, 0.0, dh)[0]
            np.testing.assert_allclose(laser_pose_W(scene, lam), expected, atol=1e-9, rtol=0)
        point, axis = hinge_axis_W(scene)
        np.testing.assert_allclose(point, T_W_M[:3, 3], atol=1e-9)
        np.testing.assert_allclose(axis, T_W_M[:3, 2], atol=1e-9)


def test_scene_fields_and_tunnel_truth() -> None:
    sc = load_scenario(REPO / "scenarios" / "tunnel_v.yaml")
    scene = build_scene(sc)
    n = len(scene.marker_ids)
    assert n == 18 and scene.marker_ids[0] == "m00" and scene.markers_W.shape == (n, 3)
    assert scene.geom_reflectivity.shape == scene.geom_is_marker.shape == (scene.model.ngeom,)
    assert scene.geom_is_marker.sum() == n
    np.testing.assert_array_equal(np.flatnonzero(scene.geom_is_marker), np.sort(scene.marker_geom_ids))
    np.testing.assert_allclose(scene.geom_reflectivity[scene.marker_geom_ids], 200.0)
    # V markers sit one radius off the wall surface, inside the tunnel
    np.testing.assert_allclose(np.abs(scene.markers_W[:, 1]), 0.39 - 0.005)
    assert scene.tunnel_truth == {"width_m": 0.78, "height_m": 2.30, "plate_distance_m": 2.24}
    rig = scene.model.geom_group >= 2
    assert rig.any() and np.all(scene.geom_reflectivity[rig] == 0) and not scene.lidar_geomgroup[2:].any()
    np.testing.assert_allclose(scene.model.body_pos[scene.body_M_id], [0.0, 0.008, 1.012])
    # the saved model carries the reflectivity
    reloaded = mujoco.MjModel.from_xml_string(scene.spec.to_xml())
    np.testing.assert_allclose(reloaded.geom_user, scene.model.geom_user)


def test_scene_xml_tunnel_matches_build_scene() -> None:
    """models/scene.xml is the nominal tunnel_v: its tunnel boxes equal those build_scene makes."""
    xml = mujoco.MjModel.from_xml_path(str(MODELS_DIR / "scene.xml"))
    built = build_scene(load_scenario(REPO / "scenarios" / "tunnel_v.yaml")).model
    names = ("tunnel_left", "tunnel_right", "tunnel_floor", "tunnel_ceiling", "plate_below", "plate_above",
             "plate_left", "plate_right")
    for name in names:
        np.testing.assert_allclose(xml.geom(name).size, built.geom(name).size, atol=1e-12)
        np.testing.assert_allclose(xml.geom(name).pos, built.geom(name).pos, atol=1e-12)
        np.testing.assert_allclose(xml.geom_user[xml.geom(name).id], built.geom_user[built.geom(name).id])


# --- (b) every model and scenario compiles and steps without warnings ------------------------------------

def _step_clean(model: mujoco.MjModel) -> None:
    data = mujoco.MjData(model)
    for _ in range(20):
        mujoco.mj_step(model, data)
    assert all(w.number == 0 for w in data.warning), [w.number for w in data.warning]


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.name)
def test_model_files_compile_and_step(path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    _step_clean(mujoco.MjModel.from_xml_path(str(path)))
    out, err = capfd.readouterr()
    assert "warning" not in (out + err).lower()


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.name)
def test_scenarios_build_and_step(path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    scene = build_scene(load_scenario(path))
    _step_clean(scene.model)
    out, err = capfd.readouterr()
    assert "warning" not in (out + err).lower()


def test_models_and_scenarios_exist() -> None:
    assert {p.name for p in MODELS} >= {"rig.xml", "scene.xml"}
    assert {p.name for p in SCENARIOS} >= {"tunnel_v.yaml", "plane_0deg.yaml", "plane_30deg.yaml"}


# --- (c) bad scenarios are rejected with the field named ---------------------------------------------------

def test_marker_inside_wall_rejected() -> None:
    d = _tunnel_dict()
    d["markers"]["layout"] = {"kind": "points", "positions": [[1.0, 0.388, 1.0]]}
    with pytest.raises(InputError, match=r"markers\.layout: marker m00 .* intersects the left wall"):
        build_scene(parse_scenario(d, "bad"))
    d["markers"]["layout"] = {"kind": "points", "positions": [[1.0, 0.0, -0.2]]}
    with pytest.raises(InputError, match=r"markers\.layout: marker m00 .* below the floor"):
        build_scene(parse_scenario(d, "bad"))


def test_overlapping_markers_rejected() -> None:
    d = _points_dict([[1.0, 0.0, 1.0], [1.0, 0.006, 1.0]])
    with pytest.raises(InputError, match=r"markers\.layout: markers m00 and m01 overlap"):
        build_scene(parse_scenario(d, "bad"))


def test_marker_off_board_rejected() -> None:
    d = yaml.safe_load((REPO / "scenarios" / "plane_0deg.yaml").read_text())
    d["markers"]["layout"]["spacing_m"] = 0.5
    with pytest.raises(InputError, match=r"markers\.layout: marker m00 .* off the"):
        build_scene(parse_scenario(d, "bad"))


def test_optical_centre_outside_tunnel_rejected() -> None:
    d = _tunnel_dict()
    d["rig"]["mount"]["y"] = 0.5
    with pytest.raises(InputError, match=r"rig\.mount: the laser's optical centre"):
        build_scene(parse_scenario(d, "bad"))


def test_manhole_outside_plate_rejected() -> None:
    d = _tunnel_dict()
    d["scene"]["tunnel"]["manhole"]["width_m"] = 1.0
    with pytest.raises(InputError, match=r"scene\.tunnel\.manhole"):
        build_scene(parse_scenario(d, "bad"))


def test_missing_and_unreadable_mesh_rejected(tmp_path: Path) -> None:
    d = _points_dict([[1.0, 0.0, 1.0]], meshes=[{"file": str(tmp_path / "nope.stl")}])
    with pytest.raises(InputError, match=r"scene\.meshes\[0\]\.file: no such file"):
        build_scene(parse_scenario(d, "bad"))
    junk = tmp_path / "junk.stl"
    junk.write_text("this is not a mesh\n")
    d = _points_dict([[1.0, 0.0, 1.0]], meshes=[{"file": str(junk)}])
    with pytest.raises(InputError, match=r"scene\.meshes\[0\]\.file: "):
        build_scene(parse_scenario(d, "bad"))


@pytest.mark.parametrize(
    ("edit", "field"),
    [
        (lambda d: d.update(colour="red"), r"colour: unknown key"),
        (lambda d: d["servo"].update(passes="two"), r"servo\.passes"),
        (lambda d: d["markers"].update(radius_m=-0.005), r"markers\.radius_m"),
        (lambda d: d["servo"].update(end_rad=d["servo"]["start_rad"]), 
         r"servo: .*start_rad and end_rad are equal"),
        (lambda d: d["markers"]["layout"].update(per_arm=0), r"markers\.layout\.per_arm"),
        (lambda d: d["servo"].update(mode="spin", passes=2), r"servo: .*passes must be 1"),
        (lambda d: d["servo"].update(mode="spin", revolutions=0), r"servo\.revolutions"),
        (lambda d: d["servo"].update(mode="turn"), r"servo\.mode"),
    ],
    ids=["unknown-key", "wrong-type", "negative-radius", "servo-limits-equal", "zero-per-arm", "spin-passes",
         "spin-zero-turns", "unknown-mode"],
)
def test_bad_yaml_rejected_by_load_scenario(tmp_path: Path, edit: Any, field: str) -> None:
    d = copy.deepcopy(_tunnel_dict())
    edit(d)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(InputError, match=rf"^{path}: {field}"):
        load_scenario(path)


# --- (d) ray casts from the laser site --------------------------------------------------------------------

def test_ray_to_wall_and_marker_analytic() -> None:
    scene = build_scene(load_scenario(REPO / "scenarios" / "tunnel_v.yaml"))
    for lam in (-1.2, 0.0, 0.7):
        p = laser_pose_W(scene, lam)[:3, 3]
        d, g = _ray(scene, p, np.array([0.0, 1.0, 0.0]))
        assert scene.model.geom(g).name == "tunnel_left"
        assert abs(d - (0.39 - p[1])) < 1e-9
        d, g = _ray(scene, p, np.array([0.0, 0.0, 1.0]))
        assert scene.model.geom(g).name == "tunnel_ceiling"
        assert abs(d - (2.30 - p[2])) < 1e-9
        for k in (0, 4, 13):
            c = scene.markers_W[k]
            d, g = _ray(scene, p, c - p)
            assert g == scene.marker_geom_ids[k]
            assert abs(d - (np.linalg.norm(c - p) - scene.marker_radius_m)) < 1e-9


@pytest.mark.parametrize("name", ["tunnel_v.yaml", "plane_30deg.yaml"])
def test_rays_never_hit_rig(name: str) -> None:
    scene = build_scene(load_scenario(REPO / "scenarios" / name))
    dirs = _fibonacci_sphere(4000)
    n = len(dirs)
    is_rig = scene.model.geom_group >= 2
    for lam in (-math.pi / 2, -0.4, 0.0, 1.1, math.pi / 2):
        p = laser_pose_W(scene, lam)[:3, 3].copy()
        gid = np.zeros(n, dtype=np.int32)
        dist = np.zeros(n)
        mujoco.mj_multiRay(scene.model, scene.data, p, dirs.ravel().copy(), scene.lidar_geomgroup, 1, -1, gid,
                           dist, None, n, 100.0)
        hit = gid[gid >= 0]
        assert len(hit) > 0 and not is_rig[hit].any()
        # without the group mask the housing around the optical centre is hit: the mask is what protects
        mujoco.mj_multiRay(scene.model, scene.data, p, dirs.ravel().copy(), None, 1, -1, gid, dist, None, n,
                           100.0)
        assert is_rig[gid[gid >= 0]].any()


# --- (e) meshes -------------------------------------------------------------------------------------------

def test_mesh_geometry_is_ray_cast(tmp_path: Path) -> None:
    import trimesh

    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "cube.stl")
    d = _tunnel_dict()
    # a 0.2 m cube (0.1 m scaled by 2) standing on the floor at x = 1.5 m, rotated 0.3 rad about z
    d["scene"]["meshes"] = [{"file": "cube.stl", "scale": 2.0, "reflectivity": 0.5,
                             "pose": {"x": 1.5, "y": -0.1, "z": 0.1, "yaw": 0.3}}]
    path = tmp_path / "mesh.yaml"
    path.write_text(yaml.safe_dump(d))
    scene = build_scene(load_scenario(path))  # relative mesh path resolved against the YAML's folder
    g_mesh = scene.model.geom("mesh0").id
    assert scene.model.geom_type[g_mesh] == mujoco.mjtGeom.mjGEOM_MESH
    assert scene.geom_reflectivity[g_mesh] == 0.5 and not scene.geom_is_marker[g_mesh]
    # ray straight down onto the cube's top face (z = 0.2)
    d_top, g = _ray(scene, np.array([1.5, -0.1, 1.0]), np.array([0.0, 0.0, -1.0]))
    assert g == g_mesh and abs(d_top - 0.8) < 1e-6
    # ray along the cube's rotated local x onto its face at 0.1 m from its centre
    u = np.array([math.cos(0.3), math.sin(0.3), 0.0])
    d_side, g = _ray(scene, np.array([1.5, -0.1, 0.1]) - 0.5 * u, u)
    assert g == g_mesh and abs(d_side - 0.4) < 1e-6
    # and from the laser site
    p = laser_pose_W(scene, 0.0)[:3, 3]
    _, g = _ray(scene, p, np.array([1.5, -0.1, 0.1]) - p)
    assert g == g_mesh


def test_v_layout_jitter_moves_each_marker_along_its_wall_by_the_seed() -> None:
    """A V's jitter_m moves every marker along the tunnel and in height by up to jitter_m, never off its wall; the
    same seed gives the same layout, another seed another (a new layout per Monte-Carlo trial, bench_study.py
    --new-layout --jitter); 0 leaves the drawn V."""
    from lrfsim.trials.variants import with_field
    from lrfsim.world.geometry import marker_centres_W

    sc = load_scenario(REPO / "scenarios" / "tunnel_v.yaml")
    assert sc.markers is not None and sc.markers.layout.kind == "v" and sc.markers.layout.jitter_m == 0.0
    drawn = marker_centres_W(sc)
    jittered = with_field(sc, "markers.layout.jitter_m", 0.03)
    moved = marker_centres_W(jittered) - drawn
    assert np.all(np.abs(moved[:, [0, 2]]) <= 0.03) and np.abs(moved[:, [0, 2]]).max() > 0.02
    assert np.all(moved[:, 1] == 0.0)  # on its wall
    np.testing.assert_array_equal(marker_centres_W(jittered), drawn + moved)
    other = marker_centres_W(jittered.model_copy(update={"seed": jittered.seed + 1})) - drawn
    assert np.abs(other - moved).max() > 0.01
