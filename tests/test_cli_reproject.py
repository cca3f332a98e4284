"""`lrfcal inspect` and `lrfcal reproject` on small synthetic bags: files written, content equal to the API's,
one-off options, calibration DH, overlapping outputs refused."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from test_bag_shapes import DH_TEST, S, write

from lrfcal.cli import main
from lrfcal.commands.reproject import POINT_DTYPE, read_cloud_ply, reproject_beams
from lrfcal.io.bag import read_bag
from lrfcal.io.rig import ScanSource, ServoSource
from lrfcal.model.kinematics import DH


def _main(monkeypatch: pytest.MonkeyPatch, argv: list[str]) -> int:
    monkeypatch.setattr(sys, "argv", ["lrfcal", *argv])
    monkeypatch.setenv("COLUMNS", "250")  # rich: no wrapping of the long lines checked below
    try:
        main()
    except SystemExit as e:
        return int(e.code or 0)
    return 0


def _rig(tmp_path: Path, dh: DH = DH_TEST, **extra: object) -> Path:
    path = tmp_path / "rig.yaml"
    path.write_text(yaml.safe_dump({"dh": dh.as_dict(), **extra}))
    return path


@pytest.fixture(scope="module")
def canonical_bag(tmp_path_factory) -> Path:
    return write(tmp_path_factory.mktemp("cli") / "bag", "mcap", "canonical")


def _expected(bag: Path, dh: DH, servo: ServoSource | None = None):
    data = read_bag(bag, ScanSource(), servo or ServoSource(joint="servo"), warn=lambda _t: None)
    return reproject_beams(data.scans, data.joints, dh)


def test_reproject_writes_ply_and_pointcloud2_bag(tmp_path, monkeypatch, canonical_bag, capsys):
    out, bag_out = tmp_path / "out" / "cloud.ply", tmp_path / "out" / "clouds"
    code = _main(monkeypatch, ["reproject", str(canonical_bag), "--nominal", str(_rig(tmp_path)), "-o", str(out),
                               "--bag-out", str(bag_out)])
    assert code == 0
    expect = _expected(canonical_bag, DH_TEST)
    ply = read_cloud_ply(out)
    assert ply.size == len(expect)
    np.testing.assert_allclose(np.c_[ply["x"], ply["y"], ply["z"]], expect.points_M, atol=1e-6)
    np.testing.assert_array_equal(ply["scan"], expect.scan)
    np.testing.assert_array_equal(ply["beam"], expect.beam)
    np.testing.assert_allclose(ply["time"], expect.times_s, rtol=0, atol=1e-6)
    np.testing.assert_allclose(ply["intensity"], expect.intensity.astype(np.float32))
    # one PointCloud2 per sweep, all points, the same layout as the PLY
    from rosbags.highlevel import AnyReader

    with AnyReader([bag_out]) as r:
        msgs = [r.deserialize(raw, c.msgtype) for c, _, raw in r.messages()]
    assert len(msgs) == np.unique(expect.sweep).size >= 2
    assert sum(m.width for m in msgs) == len(expect)
    first = np.frombuffer(msgs[0].data.tobytes(), dtype=POINT_DTYPE)
    np.testing.assert_array_equal(first, ply[: first.size])
    assert {f.name for f in msgs[0].fields} == set(POINT_DTYPE.names)
    err = capsys.readouterr().err
    assert "reprojected" in err and f"{S} scans" in err


def test_reproject_with_calibration_and_one_off_options(tmp_path, monkeypatch):
    bag = write(tmp_path / "bag", "mcap", "int32_deg")
    calib = tmp_path / "calibration.yaml"
    dh2 = DH(a=0.06, alpha=0.31, b=0.021, beta=0.09)
    calib.write_text(yaml.safe_dump({"dh": {k: {"value": v, "sigma": 0.001} for k, v in dh2.as_dict().items()}}))
    out = tmp_path / "c.ply"
    # the rig file names the canonical topics; the options point at the Int32-degree topic without header
    code = _main(monkeypatch, ["reproject", str(bag), "--nominal", str(_rig(tmp_path)), "--calibration", str(calib),
                               "--servo-topic", "/servo", "--unit", "deg", "--servo-stamp", "receive", "-o",
                               str(out)])
    assert code == 0
    expect = _expected(bag, dh2, ServoSource(topic="/servo", unit="deg", stamp="receive"))
    ply = read_cloud_ply(out)
    np.testing.assert_allclose(np.c_[ply["x"], ply["y"], ply["z"]], expect.points_M, atol=1e-6)
    nominal = _expected(bag, DH_TEST, ServoSource(topic="/servo", unit="deg", stamp="receive"))
    assert np.max(np.abs(nominal.points_M - expect.points_M)) > 1e-3  # the calibration's DH was used


@pytest.mark.parametrize("args,pattern", [
    (["--unit", "degree"], r"option unit: Input should be 'rad', 'deg' or 'counts', got 'degree'"),
    (["--servo-topic", "/nope"], r"topic /nope: not in bag \(topics: /joint_states, /scan\)"),
])
def test_reproject_bad_options_exit_2(tmp_path, monkeypatch, canonical_bag, capsys, args, pattern):
    out = tmp_path / "x.ply"
    code = _main(monkeypatch, ["reproject", str(canonical_bag), "--nominal", str(_rig(tmp_path)), "-o", str(out),
                               *args])
    assert code == 2 and not out.exists()
    import re

    assert re.search(pattern, capsys.readouterr().err)


def test_reproject_refuses_output_inside_input(tmp_path, monkeypatch, capsys):
    bag = write(tmp_path / "bag", "mcap", "canonical")
    code = _main(monkeypatch, ["reproject", str(bag), "--nominal", str(_rig(tmp_path)), "-o", str(bag / "c.ply")])
    assert code == 2 and "overlaps the input" in capsys.readouterr().err
    assert not (bag / "c.ply").exists()


def test_inspect_prints_topics_problems_and_snippet(tmp_path, monkeypatch, capsys):
    bag = write(tmp_path / "bag", "mcap", "time_increment_0")
    assert _main(monkeypatch, ["inspect", str(bag), "--no-dh"]) == 0
    out = capsys.readouterr().out
    for phrase in ("/joint_states", "sensor_msgs/msg/LaserScan", "time_increment is 0", "joint: servo",
                   "rig file"):
        assert phrase in out
    # with a rig file: its sources are used, nothing guessed
    rig = _rig(tmp_path, servo={"topic": "/joint_states", "joint": "servo"})
    assert _main(monkeypatch, ["inspect", str(bag), "--nominal", str(rig)]) == 0
    out = capsys.readouterr().out
    assert "guessed" not in out and "a: 0.05" in out


def test_reproject_applies_the_calibrations_clock_offset(tmp_path, monkeypatch, canonical_bag):
    """calibration.yaml's estimated clock offset (laser - servo) is applied unless --clock-offset is given."""
    calib = tmp_path / "calibration.yaml"
    calib.write_text(yaml.safe_dump({"dh": {k: {"value": v, "sigma": 0.001} for k, v in DH_TEST.as_dict().items()},
                                     "clock_offset_s": {"value": 0.03, "sigma": 0.0003}}))
    data = read_bag(canonical_bag, ScanSource(), ServoSource(joint="servo"), warn=lambda _t: None)
    for extra, offset in (([], 0.03), (["--clock-offset", "0"], 0.0)):
        out = tmp_path / f"c{len(extra)}.ply"
        code = _main(monkeypatch, ["reproject", str(canonical_bag), "--nominal", str(_rig(tmp_path)),
                                   "--calibration", str(calib), "-o", str(out), *extra])
        assert code == 0
        expect = reproject_beams(data.scans, data.joints, DH_TEST, offset)
        ply = read_cloud_ply(out)
        np.testing.assert_allclose(np.c_[ply["x"], ply["y"], ply["z"]], expect.points_M, atol=1e-6)
    # the calibration folder stands for its calibration.yaml, as lrfcal check takes it
    folder_out = tmp_path / "folder.ply"
    assert _main(monkeypatch, ["reproject", str(canonical_bag), "--nominal", str(_rig(tmp_path)), "--calibration",
                               str(tmp_path), "-o", str(folder_out)]) == 0
    assert folder_out.read_bytes() == (tmp_path / "c0.ply").read_bytes()


def test_reproject_takes_a_recording_folder_as_calibrate_does(tmp_path, monkeypatch, canonical_bag, capsys):
    """The folder holding bag/ (what lrfsim writes, what `lrfcal calibrate REC` takes) stands for its bag: the same
    cloud as from the bag itself (it said "a recording folder, not a bag: pass its bag")."""
    assert (canonical_bag.parent / "bag") == canonical_bag
    rig = _rig(tmp_path)
    outs = [tmp_path / "from_bag.ply", tmp_path / "from_folder.ply"]
    for given, out in zip((canonical_bag, canonical_bag.parent), outs, strict=True):
        assert _main(monkeypatch, ["reproject", str(given), "--nominal", str(rig), "-o", str(out)]) == 0, \
            capsys.readouterr().err
    np.testing.assert_array_equal(read_cloud_ply(outs[0]), read_cloud_ply(outs[1]))
    # a folder holding no bag: one line saying what was looked for and how reproject takes a bag (it has no --bag)
    empty = tmp_path / "empty"
    empty.mkdir()
    capsys.readouterr()
    assert _main(monkeypatch, ["reproject", str(empty), "--nominal", str(rig), "-o", str(tmp_path / "e.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no bag found" in err and "as BAG" in err and "--bag" not in err, err


def test_reproject_reads_a_recording_folders_own_rig_file(tmp_path, monkeypatch, canonical_bag, capsys):
    """A recording folder holds its rig file (nominal.yaml), as `lrfcal calibrate REC` reads it: reproject takes it
    without --nominal (the same cloud as with it); a bag without one, and no --nominal, is one line naming the
    option and how to get a rig file (it said "Missing option '--nominal'" for the folder too)."""
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "bag").symlink_to(canonical_bag, target_is_directory=True)
    (rec / "nominal.yaml").write_text(_rig(tmp_path).read_text())
    outs = [tmp_path / "given.ply", tmp_path / "own.ply"]
    assert _main(monkeypatch, ["reproject", str(rec), "--nominal", str(rec / "nominal.yaml"), "-o", str(outs[0])]) == 0
    assert _main(monkeypatch, ["reproject", str(rec), "-o", str(outs[1])]) == 0, capsys.readouterr().err
    np.testing.assert_array_equal(read_cloud_ply(outs[0]), read_cloud_ply(outs[1]))
    capsys.readouterr()
    assert _main(monkeypatch, ["reproject", str(canonical_bag), "-o", str(tmp_path / "b.ply")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--nominal" in err and "lrfcal inspect" in err, err
    assert not (tmp_path / "b.ply").exists()
