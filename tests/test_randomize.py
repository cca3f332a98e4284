"""The broad random-truth generator (lrfsim.testing.random_scenarios.random_scenario_wide), its scan-plane attitudes
(broad=True) and its determinability label."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from conftest import tiered

from lrfcal.config import CalibConfig
from lrfcal.model.kinematics import Pose
from lrfsim.scenario.file import load_scenario
from lrfsim.simulation.simulate import simulate
from lrfsim.testing.random_scenarios import (
    ALPHA_KINDS,
    ALPHA_RANGES_DEG,
    WIDE_AXES,
    WIDE_LAYOUTS,
    WIDE_MIN_AXIAL_SPREAD_M,
    alpha_kind_of,
    axial_spread_m,
    broad_alpha_kind,
    detected_markers,
    random_scenario,
    random_scenario_wide,
    visible_markers,
    wide_dh_determined,
    wide_dh_sigma,
)
from lrfsim.world.geometry import marker_centres_W
from lrfsim.world.scene import build_scene

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
SEEDS = range(60)


def test_deterministic_and_separate_from_random_scenario() -> None:
    assert random_scenario_wide(7) == random_scenario_wide(7)
    assert random_scenario_wide(7) != random_scenario_wide(8)
    assert random_scenario(3) == random_scenario(3)  # the recovery suite's generator is untouched
    assert random_scenario(3).name == "random_3"


def test_covers_the_requested_space() -> None:
    """Over 60 seeds: every layout and motor axis, both signs of alpha and b, beta near 0 and +-90 deg, 1-4
    passes, 6-30 markers, DH within the stated ranges."""
    scen = [random_scenario_wide(s) for s in SEEDS]
    names = Counter(sc.name.split("_", 2)[2] for sc in scen)
    assert {lay for lay in WIDE_LAYOUTS if any(n.startswith(lay) for n in names)} == set(WIDE_LAYOUTS)
    assert {ax for ax in WIDE_AXES if any(f"_{ax}_" in n for n in names)} == set(WIDE_AXES)
    alpha = np.array([sc.rig.dh.alpha for sc in scen])
    beta = np.array([sc.rig.dh.beta for sc in scen])
    b = np.array([sc.rig.dh.b for sc in scen])
    a = np.array([sc.rig.dh.a for sc in scen])
    assert np.all(np.abs(np.abs(alpha) - math.pi / 2) <= math.radians(3.0) + 1e-12)
    assert (alpha > 0).any() and (alpha < 0).any() and (b > 0).any() and (b < 0).any()
    near = [np.abs(beta - c) <= math.radians(3.0) + 1e-12 for c in (0.0, math.pi / 2, -math.pi / 2)]
    assert np.all(near[0] | near[1] | near[2]) and all(m.any() for m in near)
    assert np.all(np.abs(a) <= 0.02) and np.all(np.abs(b) <= 0.04)
    assert {sc.servo.passes for sc in scen} == {1, 2, 3, 4}
    n_markers = [len(marker_centres_W(sc)) for sc in scen]
    assert min(n_markers) >= 6 and max(n_markers) <= 30
    # the nominal start is off the truth, by at most 3 mm / 3 deg in the DH parameters
    for sc in scen:
        d = np.array([sc.rig.nominal_dh.a - sc.rig.dh.a, sc.rig.nominal_dh.b - sc.rig.dh.b])
        assert np.all(np.abs(d) <= 0.003) and abs(sc.rig.nominal_dh.alpha - sc.rig.dh.alpha) <= math.radians(3.0)


def test_scenes_build_and_markers_in_view() -> None:
    """The simulator accepts every generated scenario, and the sweep can see >= 6 markers of each (geometry)."""
    for s in range(20):
        sc = random_scenario_wide(s)
        build_scene(sc)
    few = [s for s in SEEDS if visible_markers(random_scenario_wide(s)).sum() < 6]
    assert len(few) <= 0.05 * len(SEEDS), few


def test_forced_choices() -> None:
    sc = random_scenario_wide(5, layout="board", axis="vertical", beta_deg=0.0, passes=1)
    assert sc.scene.board is not None and sc.scene.tunnel is None and sc.servo.passes == 1
    assert abs(sc.rig.dh.beta) <= math.radians(3.0) + 1e-12
    z_M = sc.rig.mount.to_pose().matrix()[:3, 2]
    assert abs(abs(z_M[2]) - 1.0) < 1 - math.cos(math.radians(6.0))  # motor axis vertical (5 deg jitter)
    with pytest.raises(ValueError, match="layout"):
        random_scenario_wide(5, layout="sphere")


def test_simulated_markers_are_detected() -> None:
    """One quick simulation: intensity blobs are found on (nearly) every marker the geometry says is visible."""
    sc = random_scenario_wide(4, passes=1)  # 16 markers scattered in the tunnel, motor axis along it
    seen = detected_markers(simulate(sc), sc)
    assert len(seen) >= max(6, int(visible_markers(sc).sum()) - 1), (len(seen), visible_markers(sc).sum())


def test_determinability_label() -> None:
    """Shipped layouts determine the DH parameters; a board ACROSS the motor axis (every marker at one axial
    distance) does not; the label's point-model sigma is finite and ordered accordingly."""
    plane = load_scenario(SCENARIOS / "plane_0deg.yaml")
    assert wide_dh_determined(plane) and wide_dh_determined(load_scenario(SCENARIOS / "tunnel_v.yaml"))
    # the same board turned to face the rig along the motor axis (+x_W), 1.5 m ahead
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])  # front face to -x_W
    T[:3, 3] = (1.5, 0.0, 1.0)
    p = Pose.from_matrix(T)
    board = plane.scene.board
    assert board is not None
    across = plane.model_copy(update={"scene": plane.scene.model_copy(update={"board": board.model_copy(
        update={"pose": board.pose.model_copy(update={"x": p.x, "y": p.y, "z": p.z, "roll": p.roll,
                                                      "pitch": p.pitch, "yaw": p.yaw})})})})
    assert visible_markers(across).sum() >= 20
    assert axial_spread_m(across) < 0.01 < WIDE_MIN_AXIAL_SPREAD_M < axial_spread_m(plane)
    assert not wide_dh_determined(across)
    assert np.all(wide_dh_sigma(plane) < wide_dh_sigma(across))
    labels = [wide_dh_determined(random_scenario_wide(s)) for s in SEEDS]
    assert 0.4 < np.mean(labels) < 0.95  # both kinds are generated
    # a V on the one wall that the motor axis points at: every marker at about one axial distance
    one_wall = [random_scenario_wide(s, layout="v_one_wall", axis="across") for s in range(5)]
    assert not any(wide_dh_determined(sc) for sc in one_wall)


def test_broad_draws_every_scan_plane_attitude_with_markers_in_view() -> None:
    """broad=True: a third each of alpha along the motor axis (as the default draws, the same scenarios), tilted
    (|alpha| 20-70 deg) and near perpendicular (|alpha| 0-15 deg, spinning), either sign; every marker in view of
    the sweep or spin (geometry), at least 6; the nominal start within 3 deg of the true alpha and beta."""
    scen = [random_scenario_wide(s, broad=True) for s in SEEDS]
    assert Counter(alpha_kind_of(sc) for sc in scen) == {k: len(SEEDS) // 3 for k in ALPHA_KINDS}
    for s, sc in zip(SEEDS, scen, strict=True):
        kind, alpha = broad_alpha_kind(s), abs(math.degrees(sc.rig.dh.alpha))
        assert alpha_kind_of(sc) == kind, sc.name
        if kind == "axis":
            assert sc == random_scenario_wide(s)
        else:
            lo, hi = ALPHA_RANGES_DEG[kind]
            assert lo <= alpha <= hi and kind in sc.name, (sc.name, alpha)
        if kind == "near_perpendicular":
            assert sc.servo.mode == "spin", sc.name
        vis = visible_markers(sc)
        assert vis.sum() >= 6 and (kind == "axis" or vis.all()), (sc.name, vis)
        nominal, truth = sc.rig.nominal_dh, sc.rig.dh
        assert max(abs(nominal.alpha - truth.alpha), abs(nominal.beta - truth.beta)) <= math.radians(3.0) + 1e-12
    for kind in ("tilted", "near_perpendicular"):
        alpha = np.array([sc.rig.dh.alpha for sc in scen if alpha_kind_of(sc) == kind])
        assert (alpha > 0).any() and (alpha < 0).any(), kind
    assert {sc.servo.mode for sc in scen if alpha_kind_of(sc) == "tilted"} == {"sweep", "spin"}
    for sc in scen[1:3]:
        build_scene(sc)
    forced = random_scenario_wide(3, alpha_kind="tilted", axis="along")
    assert alpha_kind_of(forced) == "tilted" and "_along_" in forced.name
    with pytest.raises(ValueError, match="alpha_kind"):
        random_scenario_wide(3, alpha_kind="flat")
    with pytest.raises(ValueError, match="layout"):
        random_scenario_wide(3, alpha_kind="tilted", layout="board")


def test_near_perpendicular_truth_is_calibrated_within_4_sigma(tmp_path: Path) -> None:
    """A near-perpendicular random truth (alpha -4 deg, spinning): its markers are seen, and the calibration comes
    back within 4 sigma (before the marker map's uncertainty and the per-marker widening entered the sigma, such
    truths came back 5-9 sigma off and were refused by an attitude limit). Its spin turns on some markers (the band
    a tilted plane sweeps ends there), and that model error joins its sigma near perpendicular too
    (lrfcal.stages.markers.MarkerWay.systematics; once held back within 15 deg of perpendicular)."""
    from lrfsim.simulation.recording import write_recording
    from lrfsim.trials.trial import calibrate_recording

    sc = random_scenario_wide(2, broad=True)
    assert alpha_kind_of(sc) == "near_perpendicular" and sc.servo.mode == "spin"
    result = simulate(sc)
    assert len(detected_markers(result, sc)) >= int(visible_markers(sc).sum()) - 1
    write_recording(result, sc, tmp_path / sc.name)
    # the drawing to 2 deg: the nominal (alpha -4.75 deg) then tells the rig (-4.0 deg) from its mirror image
    # (+4.0 deg); with the default 5 deg it cannot, and the calibration refuses naming the mirror image
    # (tests/test_checks.py)
    config = CalibConfig(dh_tolerance=(0.010, math.radians(2.0), 0.010, math.radians(2.0)))
    trial = calibrate_recording(tmp_path / sc.name, config, keep_result=True)
    assert abs(math.degrees(sc.rig.dh.alpha)) < 15.0
    assert trial.status == "calibrated", trial.describe()
    assert np.all(np.abs(trial.z) < 4.0), trial.describe()
    assert trial.result is not None
    assert any("turn on some markers" in n for n in trial.result.notes), trial.result.notes


@pytest.mark.parametrize(("seed", "recording_seed"), tiered([(8, None), (14, 1007)]))
def test_near_perpendicular_truth_in_the_maps_other_handedness(tmp_path: Path, seed: int,
                                                               recording_seed: int | None) -> None:
    """Near perpendicular the association cannot tell the marker map's handedness: seed 8 (alpha -9.6 deg) landed on
    the rig's mirror image (alpha +9.6 deg, 4.3 nominal tolerances off), which the mirror check refused. The
    nominal DH now choose the handedness: solved again in the map's mirror image, within 4 sigma, and said so.
    Truth 14 recorded with seed 1007 (a Monte-Carlo trial of `lrfsim study --recast`), solved so, ended in the
    rig's other DH representative (-a, -alpha, b, beta + pi, the mount turned by pi: the same rig), 435-894 sigma
    off the rig file's DH as reported; it is now solved once more from that twin, in the nominal's representative."""
    from lrfsim.simulation.recording import write_recording
    from lrfsim.trials.trial import calibrate_recording

    sc = random_scenario_wide(seed, broad=True)
    if recording_seed is not None:
        sc = sc.model_copy(update={"seed": recording_seed})
    assert alpha_kind_of(sc) == "near_perpendicular"
    write_recording(simulate(sc), sc, tmp_path / sc.name)
    trial = calibrate_recording(tmp_path / sc.name, keep_result=True)
    assert trial.status == "calibrated", trial.describe()
    assert np.all(np.abs(trial.z) < 4.0), trial.describe()
    assert trial.result is not None
    assert any("other handedness" in n for n in trial.result.notes), trial.result.notes
