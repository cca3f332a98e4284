"""simulate() timing and truth, the recording folder read back with rosbags (every field), atomic writes, tape."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

import lrfsim.simulation.recording as recording
from lrfcal.errors import InputError
from lrfcal.io.files import MANIFEST_NAME
from lrfsim.scenario.file import Scenario, load_scenario, parse_scenario
from lrfsim.sensors.lidar import beam_times
from lrfsim.sensors.servo import sweep_trajectory
from lrfsim.sensors.tape import affine_dimension, is_rigid, measure_tape
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import SimResult, simulate

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def _scenario(**servo: object) -> Scenario:
    data = yaml.safe_load((SCENARIOS / "tunnel_v.yaml").read_text())
    data = copy.deepcopy(data)
    data["servo"].update({"start_rad": 0.05, "end_rad": -0.05, "passes": 1, "settle_s": 0.05, **servo})
    data["tape"] = {"sigma_m": 0.001, "pair_fraction": 0.3}
    return parse_scenario(data, "test")


@pytest.fixture(scope="module")
def sim() -> tuple[Scenario, SimResult]:
    sc = _scenario(clock_offset_s=0.137, rate_hz=50.0, backlash_rad=0.002)
    return sc, simulate(sc)


def test_stream_timing_and_clock_offset(sim: tuple[Scenario, SimResult]) -> None:
    sc, res = sim
    assert np.allclose(np.diff(res.scan_stamps_s), 0.025, atol=1e-12)
    assert np.allclose(np.diff(res.joints.stamps_s), 1 / 50.0, atol=1e-12)
    # laser stamp = servo time of beam 0 + offset: the per-beam angles are the trajectory at servo time
    traj = sweep_trajectory(sc.servo)
    servo_t = beam_times(res.scan_stamps_s - 0.137, sc.sensor)
    assert np.allclose(res.beam_lambda_rad, traj.angle(servo_t), atol=1e-12)
    assert 0.137 <= res.scan_stamps_s[0] < 0.137 + 0.025
    assert res.truth.clock_offset_s == 0.137
    assert res.ranges_m.shape == (res.scan_stamps_s.size, 1081)
    assert res.stats.max_origin_error_m < 1e-6


def test_bag_reads_back_with_every_field(sim: tuple[Scenario, SimResult], tmp_path: Path) -> None:
    sc, res = sim
    out = write_recording(res, sc, tmp_path / "rec")
    assert sorted(p.name for p in out.iterdir()) == sorted([MANIFEST_NAME, "bag", "distances.csv",
                                                            "ground_truth.yaml", "nominal.yaml", "scenario.yaml"])
    scans, joints = [], []
    with AnyReader([out / "bag"]) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {
            "/scan": "sensor_msgs/msg/LaserScan", "/joint_states": "sensor_msgs/msg/JointState"}
        last = 0
        for conn, t, raw in reader.messages():
            assert t >= last
            last = t
            msg = reader.deserialize(raw, conn.msgtype)
            (scans if conn.topic == "/scan" else joints).append(msg)
    assert len(scans) == res.scan_stamps_s.size and len(joints) == res.joints.stamps_s.size
    m = scans[3]
    assert m.header.frame_id == "laser"
    ns = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
    assert ns == recording.EPOCH_NS + round(res.scan_stamps_s[3] * 1e9)
    assert m.angle_min == pytest.approx(-2.35619449, abs=1e-8)
    assert m.angle_max == pytest.approx(2.35619449, abs=1e-8)
    assert m.angle_increment == pytest.approx(0.00436332313, abs=1e-10)
    assert m.time_increment == pytest.approx(0.025 / 1440)
    assert m.scan_time == pytest.approx(0.025)
    assert (m.range_min, m.range_max) == (pytest.approx(0.023), 60.0)
    assert m.ranges.dtype == np.float32 and m.ranges.size == 1081
    assert np.array_equal(m.ranges, res.ranges_m[3].astype(np.float32), equal_nan=True)
    assert np.isnan(m.ranges).any()  # no return is NaN (the manhole, the open end)
    assert np.array_equal(m.intensities, res.intensities[3].astype(np.float32))
    j = joints[7]
    assert list(j.name) == ["servo"] and j.effort.size == 0
    assert j.position[0] == res.joints.positions_rad[7] and j.velocity[0] == res.joints.velocities_rad_s[7]
    assert j.header.stamp.sec * 10**9 + j.header.stamp.nanosec == recording.EPOCH_NS + round(
        res.joints.stamps_s[7] * 1e9)

    # the side files
    rows = (out / "distances.csv").read_text().splitlines()
    assert rows[0] == "marker_i,marker_j,distance_m" and len(rows) == 1 + res.tape.pairs.shape[0]
    nominal = yaml.safe_load((out / "nominal.yaml").read_text())
    assert nominal["dh"] == sc.rig.nominal_dh.model_dump() and nominal["servo"]["joint"] == "servo"
    assert (nominal["scan"]["topic"], nominal["servo"]["topic"], nominal["marker_radius_m"]) == (
        "/scan", "/joint_states", 0.005)
    truth = yaml.safe_load((out / "ground_truth.yaml").read_text())
    assert truth["dh"] == sc.rig.dh.model_dump() and truth["mount"] == sc.rig.mount.model_dump()
    assert np.allclose(truth["markers"]["m04"], res.truth.markers_W[4])
    assert truth["clock_offset_s"] == 0.137
    assert truth["tunnel"] == {"width_m": 0.78, "height_m": 2.3, "plate_distance_m": 2.24}
    assert load_scenario(out / "scenario.yaml") == sc


def test_atomic_writes(sim: tuple[Scenario, SimResult], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sc, res = sim
    out = tmp_path / "rec"
    write_recording(res, sc, out)
    before = (out / "distances.csv").read_text()
    with pytest.raises(InputError, match="use --overwrite"):
        write_recording(res, sc, out)
    # a failure half-way leaves the old recording untouched and no temporary folder behind
    def boom(*a: object) -> None:
        raise RuntimeError("disk full")

    monkeypatch.setattr(recording, "ground_truth_yaml", boom)
    with pytest.raises(RuntimeError):
        write_recording(res, sc, out, overwrite=True)
    assert (out / "distances.csv").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]
    with pytest.raises(RuntimeError):
        write_recording(res, sc, tmp_path / "new")
    assert not (tmp_path / "new").exists()
    monkeypatch.undo()
    # overwrite replaces our own recording atomically, never a file we did not write; an empty folder is fine
    write_recording(res, sc, out, overwrite=True)
    (out / "mine.txt").write_text("x")
    with pytest.raises(InputError, match=r"did not write \(mine.txt\)"):
        write_recording(res, sc, out, overwrite=True)
    assert (out / "mine.txt").read_text() == "x"
    (out / "mine.txt").unlink()
    (tmp_path / "empty").mkdir()
    write_recording(res, sc, tmp_path / "empty")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "rec"]


def test_tape_subset_is_rigid_and_noisy(sim: tuple[Scenario, SimResult]) -> None:
    _, res = sim
    n = len(res.truth.marker_ids)
    deg = np.bincount(res.tape.pairs.ravel(), minlength=n)
    assert deg.min() >= 4 and res.tape.pairs.shape[0] < n * (n - 1) // 2
    assert is_rigid(res.truth.markers_W, res.tape.pairs)
    from lrfsim.scenario.sections import TapeConfig

    pts = np.random.default_rng(0).uniform(-1, 1, (12, 3))
    t = measure_tape(tuple(f"p{i}" for i in range(12)), pts, TapeConfig(sigma_m=0.002), np.random.default_rng(1))
    assert t.pairs.shape == (66, 2)
    err = t.distances_m - np.linalg.norm(pts[t.pairs[:, 0]] - pts[t.pairs[:, 1]], axis=1)
    assert 0.001 < err.std() < 0.003
    flat = pts.copy()
    flat[:, 2] = 0
    assert affine_dimension(flat) == 2
    t2 = measure_tape(t.marker_ids, flat, TapeConfig(pair_fraction=0.2), np.random.default_rng(2))
    assert is_rigid(flat, t2.pairs)


def _differences(a: object, b: object, path: str = "") -> list[str]:
    """The fields (dotted paths) in which two dataclass trees differ (arrays compared exactly, NaN equal to NaN)."""
    import dataclasses

    if dataclasses.is_dataclass(a) and not isinstance(a, type):
        return [d for f in dataclasses.fields(a) for d in _differences(getattr(a, f.name), getattr(b, f.name),
                                                                          f"{path}.{f.name}")]
    if isinstance(a, np.ndarray):
        same = isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        return [] if same else [path]
    return [] if a == b else [path]


def test_in_memory_bag_reads_as_the_written_bag(sim: tuple[Scenario, SimResult], tmp_path: Path) -> None:
    """A study's trial reads the simulation's messages from memory (recording.in_memory_bag): the Recording is the
    one the written bag gives, field by field and bit by bit, but for the names of where it came from."""
    from lrfcal.io.recording import read_recording

    sc, res = sim
    from_file = read_recording(write_recording(res, sc, tmp_path / "file"))
    folder = write_recording(res, sc, tmp_path / "memory", bag=False)
    assert not (folder / "bag").exists()
    from_memory = read_recording(folder, bag_reader=recording.in_memory_bag(res, sc))
    assert sorted(_differences(from_file, from_memory)) == [".report.bag", ".scans.source", ".source"]
    assert from_memory.report.bag == "simulated bag"
    with pytest.raises(InputError, match="topics /nope and /joint_states expected"):
        read_recording(folder, bag_reader=recording.in_memory_bag(res, sc), scan_topic="/nope")
