"""What a real rig's recording does wrong (issue 54, items 3 and 4), through the INSTALLED console script as a user
meets it: a clock that steps halfway through (lrfsim's joint_clock_step_s / scan_clock_step_s faults), a bag cut
short (an MCAP file and a ROS 1 bag truncated to 70 % of their bytes, a sqlite3 bag whose write-ahead log was not
merged), a bag under another name than bag/ in the recording folder.

The servo clock steps are written into copies of the shipped plane_30deg and tunnel_v recordings (simulated once per
test run for several modules, tests/conftest.py), the scan clock step by lrfsim's fault on a short plane_30deg sweep
(about 370 scans), on which the cut bags run too.
"""

from __future__ import annotations

import copy
import re
import shutil
import sqlite3
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import tiered
from test_cli_usage import ROOT, _one_error_line, _run

from lrfcal.errors import CalibrationError
from lrfcal.io.bag import read_bag
from lrfcal.io.clocksteps import clock_cut
from lrfsim.scenario.file import Scenario, parse_scenario


def _scenario(name: str, faults: dict[str, object], short: bool = False) -> Scenario:
    data = copy.deepcopy(yaml.safe_load((ROOT / "scenarios" / f"{name}.yaml").read_text()))
    data["name"] = f"{name}-{'-'.join(faults) or 'clean'}"
    if short:
        data["servo"]["speed_rad_s"] = 0.785  # 45 deg/s: 2 passes of +-90 deg in about 370 scans
    data["faults"] = faults
    return parse_scenario(data, f"{name}.yaml")


def _errors(proc) -> list[str]:
    assert "Traceback" not in proc.stderr, proc.stderr
    return [line for line in proc.stderr.splitlines() if line.startswith("error:")]


# --- clock steps --------------------------------------------------------------------------------------------------

def _servo_clock_stepped(rec: Path, dst: Path, step_s: float, at_s: float) -> Path:
    """A copy of recording ``rec`` whose JointState stamps from ``at_s`` after its first message on are ``step_s``
    later (the servo computer's clock stepped), their receive times not: what lrfsim's ``joint_clock_step_s`` fault
    writes, made from a recording the session has simulated anyway (the CDR header stamp: sec int32, nanosec uint32
    after the 4-byte encapsulation header)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    dst.mkdir()
    for name in ("nominal.yaml", "distances.csv", "ground_truth.yaml"):
        if (rec / name).is_file():
            shutil.copy(rec / name, dst / name)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([rec / "bag"]) as reader, Writer(dst / "bag", version=9,
                                                      storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=ts) for c in reader.connections}
        t0 = reader.start_time
        for c, t_ns, raw in reader.messages():
            if c.msgtype == "sensor_msgs/msg/JointState" and t_ns - t0 >= at_s * 1e9:
                sec, nsec = struct.unpack_from("<iI", raw, 4)
                ns = sec * 10**9 + nsec + round(step_s * 1e9)
                raw = raw[:4] + struct.pack("<iI", ns // 10**9, ns % 10**9) + raw[12:]
            writer.write(conns[c.id], t_ns, raw)
    return dst


@pytest.mark.parametrize("name", tiered(["plane_30deg", "tunnel_v"]))  # tunnel_v in the slow tier
def test_a_servo_clock_step_keeps_one_side_and_its_offset_is_the_truth_there(
        name: str, shipped_recording: Callable[[str], Path], tmp_path: Path) -> None:
    """The servo computer's clock steps back 0.4 s a third of the way through (an NTP correction): the step is named,
    the longer side kept, and the offset stated is within 3 sigma of that side's truth (never one offset for both:
    before the step 0, after it +0.4 s)."""
    rec = _servo_clock_stepped(shipped_recording(name), tmp_path / "rec", -0.4, 12.0)
    out = tmp_path / "cal"
    proc = _run("lrfcal", "calibrate", rec, "-o", out, "--no-baseline", "--no-figures", timeout=600)
    assert proc.returncode == 0 and not _errors(proc), proc.stderr
    assert "clock step: the servo stamps" in proc.stderr and "step by -0.400 s" in proc.stderr, proc.stderr
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    note = next(n for n in cal["notes"] if n.startswith("clock step"))
    after = re.search(r"\(([\d.]+ s|start) to ([\d.]+ s|end) after", note)
    assert after is not None, note
    truth = 0.4 if after.group(2) == "end" else 0.0
    tau, sigma = cal["clock_offset_s"]["value"], cal["clock_offset_s"]["sigma"]
    assert sigma is not None and abs(tau - truth) < 3 * sigma, (tau, sigma, truth, note)
    assert "laser-minus-servo offset changes there by +0.400 s" in note


def test_a_scan_clock_jump_forward_is_found_alike(recording_of: Callable[[Scenario], Path]) -> None:
    rec = recording_of(_scenario("plane_30deg", {"scan_clock_step_s": 0.3, "scan_clock_step_at_s": 8.0}, short=True))
    warned: list[str] = []
    data = read_bag(rec / "bag", warn=warned.append)
    (note,) = data.report.left_out
    assert warned == [note] and "clock step: the scan stamps" in note and "step by +0.300 s" in note, note
    assert "changes there by +0.300 s" in note, note  # the laser clock later: laser-minus-servo larger
    t = data.scans.stamps_s - 1_700_000_000.0  # lrfsim.simulation.recording.EPOCH_NS
    assert "(start to 8.0" in note and t.max() < 8.0 + 0.1 and t.size == 320, note  # the longer side: before


def _stream(n: int, period: float, jitter: float, rng: np.random.Generator, t0: float = 0.0
            ) -> tuple[np.ndarray, np.ndarray]:
    stamps = t0 + period * np.arange(n)
    return stamps + 0.002 + jitter * rng.random(n), stamps


def test_clock_cut_tells_a_recorder_step_from_a_stream_step_and_refuses_a_patchwork() -> None:
    rng = np.random.default_rng(5)
    scan_r, scan_s = _stream(800, 0.025, 0.003, rng)
    servo_r, servo_s = _stream(2000, 0.01, 0.001, rng)
    plain = clock_cut(scan_r, scan_s, servo_r, servo_s, "bag: /scan", "bag: /joint_states")
    assert plain.keep_scans.all() and plain.keep_servo.all() and not plain.notes  # jitter is no step
    # the recorder's clock steps back 0.3 s at 10 s: both streams' receive times alike: nothing cut
    rec = clock_cut(scan_r - 0.3 * (scan_r > 10), scan_s, servo_r - 0.3 * (servo_r > 10), servo_s, "s", "j")
    assert rec.keep_scans.all() and rec.keep_servo.all()
    assert len(rec.notes) == 1 and "the recorder's clock" in rec.notes[0], rec.notes
    # the servo's stamps step forward 0.05 s at 14 s: the longer part (before) kept, named with its size
    cut = clock_cut(scan_r, scan_s, servo_r, servo_s + 0.05 * (servo_s > 14), "s", "j")
    assert abs(int(cut.keep_scans.sum()) - 560) <= 2 and not cut.keep_servo[servo_s > 14.01].any()
    assert "step by +0.050 s" in cut.notes[0] and "changes there by -0.050 s" in cut.notes[0], cut.notes
    # the servo's clock steps by 0.1 s every 2 s: no part with one offset holds a quarter of the scans
    with pytest.raises(CalibrationError, match=r"clock step: .* holds only \d+ of 800 scans"):
        clock_cut(scan_r, scan_s, servo_r, servo_s - 0.1 * np.floor(servo_s / 2), "s", "j")


# --- bags cut short, bags under other names -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def short_rec(recording_of: Callable[[Scenario], Path]) -> Path:
    return recording_of(_scenario("plane_30deg", {}, short=True))


def _copy_cut(rec: Path, dst: Path, fraction: float) -> Path:
    shutil.copytree(rec, dst)
    bag = next((dst / "bag").glob("*.mcap"))
    data = bag.read_bytes()
    bag.write_bytes(data[:int(fraction * len(data))])
    return dst


def test_an_mcap_cut_at_70_percent_calibrates_on_what_was_recorded(short_rec: Path, tmp_path: Path) -> None:
    rec = _copy_cut(short_rec, tmp_path / "rec", 0.7)
    out = tmp_path / "cal"
    proc = _run("lrfcal", "calibrate", rec, "-o", out, "--no-baseline", "--no-figures", timeout=600)
    assert "File end magic" not in proc.stderr and proc.returncode in (0, 3), proc.stderr
    said = re.search(r"cut short \(no footer.*?\): read up to its last complete record, \d+ of \d+ bytes \(\d+%\): "
                     r"(\d+) messages of the (\d+) its metadata.yaml lists, [\d.]+ s", " ".join(proc.stderr.split()))
    assert said is not None and 0 < int(said.group(1)) < int(said.group(2)), proc.stderr
    if proc.returncode == 0:
        assert any("cut short" in n for n in yaml.safe_load((out / "calibration.yaml").read_text())["notes"])
    else:
        assert len(_errors(proc)) == 1 and "cut short" in _errors(proc)[0], proc.stderr
    cut = _copy_cut(short_rec, tmp_path / "cut5", 0.05)  # before the end of the first chunk: nothing to recover
    line = _one_error_line(_run("lrfcal", "inspect", cut / "bag"))
    assert "cut short" in line and "no message to recover" in line and "magic" not in line, line


def test_a_ros1_bag_cut_short_in_the_recording_folder_is_found_and_read(short_rec: Path, tmp_path: Path) -> None:
    from rosbags.convert import convert
    from rosbags.typesys import Stores, get_typestore

    rec = tmp_path / "rec"
    rec.mkdir()
    for name in ("nominal.yaml", "distances.csv"):
        shutil.copy(short_rec / name, rec / name)
    bag = tmp_path / "run1.bag"
    convert([short_rec / "bag"], bag, None, 0, None, "file", None, get_typestore(Stores.ROS1_NOETIC), [], [], [], [])
    whole = read_bag(bag, warn=lambda _t: None)
    data = bag.read_bytes()
    (rec / "run1.bag").write_bytes(data[:int(0.7 * len(data))])  # the rig lost power: no index at the end
    out = tmp_path / "cal"
    proc = _run("lrfcal", "calibrate", rec, "-o", out, "--no-baseline", "--no-figures", timeout=600)
    text = " ".join(proc.stderr.split())
    assert proc.returncode in (0, 3) and "cut short (no index: the bag header's index_pos is" in text, proc.stderr
    assert re.search(r"read up to its last complete record, \d+ of \d+ bytes \(\d+%\): \d+ messages, [\d.]+ s", text)
    part = read_bag(rec / "run1.bag", warn=lambda _t: None)
    n = part.scans.stamps_s.size
    assert 0.5 * whole.scans.stamps_s.size < n < whole.scans.stamps_s.size
    np.testing.assert_array_equal(part.scans.ranges_m, whole.scans.ranges_m[:n])  # what was read is what was written
    # the folder's one bag is found; with a second one, both are named and --bag chooses
    shutil.copy(next((short_rec / "bag").glob("*.mcap")), rec / "x.mcap")
    line = _one_error_line(_run("lrfcal", "calibrate", rec, "-o", tmp_path / "cal2"))
    assert "run1.bag" in line and "x.mcap" in line and "--bag" in line, line
    (rec / "run1.bag").unlink()
    (rec / "x.mcap").unlink()
    line = _one_error_line(_run("lrfcal", "calibrate", rec, "-o", tmp_path / "cal2"))
    assert "no bag found" in line and "bag/" in line and ".bag" in line and "--bag" in line, line


def test_a_sqlite_bag_with_its_write_ahead_log_is_read_whole_and_left_as_it_was(short_rec: Path,
                                                                                tmp_path: Path) -> None:
    from rosbags.convert import convert

    full = tmp_path / "full"
    convert([short_rec / "bag"], full, "sqlite3", 8, None, "file", None, None, [], [], [], [])
    db = next(full.glob("*.db3"))
    con = sqlite3.connect(db)
    rows = con.execute("SELECT id, topic_id, timestamp, data FROM messages ORDER BY id").fetchall()
    con.execute("DELETE FROM messages WHERE id > ?", (rows[len(rows) // 2][0],))
    con.commit()
    con.execute("VACUUM")
    con.close()
    con = sqlite3.connect(db)  # the second half in the log, which a recorder that lost power leaves unmerged
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA wal_autocheckpoint=0")
    con.executemany("INSERT INTO messages VALUES (?, ?, ?, ?)", rows[len(rows) // 2 + 1:])
    con.commit()
    bag = tmp_path / "bag"
    bag.mkdir()
    for p in full.iterdir():
        if not p.name.endswith("-shm"):
            shutil.copy(p, bag / p.name)
    con.close()
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    notes: list[str] = []
    data = read_bag(bag, warn=notes.append)
    assert data.scans.stamps_s.size == read_bag(short_rec / "bag", warn=lambda _t: None).scans.stamps_s.size
    assert any("write-ahead log" in n for n in notes), notes
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before  # the input untouched
