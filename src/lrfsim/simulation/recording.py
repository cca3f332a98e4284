"""Write a simulated recording folder exactly as docs/formats.md specifies, atomically.

    DIR/bag/            ROS 2 bag (version 9, MCAP; lrfcal.io.mcap_write): /scan LaserScan, /joint_states JointState
                        (and, with sensor.echoes.enabled, /echoes MultiEchoLaserScan)
    DIR/distances.csv   marker_i,marker_j,distance_m (not written for a marker-less scene: no tape distances)
    DIR/nominal.yaml    the rig file: nominal DH and mount, marker radius (with markers), scan and servo sources
    DIR/ground_truth.yaml, DIR/scenario.yaml

Stamps: the simulation's times (seconds from the start of the sweep) are offset by :data:`EPOCH_NS`
(2023-11-14 22:13:20 UTC) so the bag carries realistic ROS times; header stamps are exact integers of ns.
Bag (log) times are the recorder's clock, taken to be the servo clock: a JointState is logged at its stamp, a
LaserScan when urg_node would publish it, at the end of the scan (servo time of beam 0 + scan_time); a clock step
lrfsim.simulation.faults injects moves the stamps only, never the log times (lrfsim.simulation.faults.true_stamps).

Atomicity: everything is written into a hidden temporary folder next to DIR, which is renamed onto DIR when
complete (an existing DIR is first moved aside and deleted after the rename, only with ``overwrite`` and only when
this project wrote everything in it: see lrfcal.io.files.check_replaceable); on any
error the temporary folder is removed, so DIR is either the old content or the complete new recording.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from numpy.typing import NDArray

from lrfcal.io.files import atomic_folder, check_replaceable, check_writable
from lrfcal.io.multiecho import MULTIECHO_TYPE, Echoes, Header, MultiEchoScan, Stamp, encode_cdr
from lrfcal.io.wire import SCAN_FLOATS
from lrfsim.scenario.file import Scenario, dump_scenario
from lrfsim.sensors.lidar import typical_range_sigma

from .faults import true_stamps

if TYPE_CHECKING:
    from lrfcal.io.bag import BagData, BagReader
    from lrfcal.io.rig import ScanSource, ServoSource

    from .result import SimResult

#: ROS time of t = 0 of the simulation [ns].
EPOCH_NS = 1_700_000_000 * 10**9
SCAN_TOPIC = "/scan"
JOINT_TOPIC = "/joint_states"
LASER_FRAME = "laser"
LASERSCAN_TYPE = "sensor_msgs/msg/LaserScan"
JOINTSTATE_TYPE = "sensor_msgs/msg/JointState"


def _ns(t_s: float) -> int:
    return EPOCH_NS + int(round(t_s * 1e9))


def check_output(out_dir: str | Path, overwrite: bool) -> Path:
    """Refuse an output folder that must not be written (see :func:`lrfcal.io.files.check_replaceable`: an
    existing non-empty folder only with ``overwrite`` and only if this project wrote all of it); return it."""
    return check_writable(check_replaceable(out_dir, overwrite))


def write_recording(result: SimResult, scenario: Scenario, out_dir: str | Path, *, overwrite: bool = False,
                    bag: bool = True) -> Path:
    """Write the recording folder of ``result`` to ``out_dir`` atomically (module docstring); return it. ``bag``
    False: everything but the bag, whose messages are then read from memory (:func:`in_memory_bag`; a study's trials
    no longer do: they write and read their bag as a real recording's)."""
    out = check_output(out_dir, overwrite).absolute()
    with atomic_folder(out, "lrfsim simulate") as tmp:
        if bag:
            write_bag(result, scenario, tmp / "bag")
        if scenario.markers is not None:
            (tmp / "distances.csv").write_text(distances_csv(result), encoding="utf-8")
        sigma = typical_range_sigma(result.ranges_m, scenario.sensor)  # the declared (spec) noise, faults aside
        (tmp / "nominal.yaml").write_text(nominal_yaml(scenario, result.truth.marker_radius_m, sigma),
                                          encoding="utf-8")
        (tmp / "ground_truth.yaml").write_text(ground_truth_yaml(result), encoding="utf-8")
        (tmp / "scenario.yaml").write_text(dump_scenario(scenario), encoding="utf-8")
    return out


def write_bag(result: SimResult, scenario: Scenario, path: Path, *, bulk: bool = True) -> None:
    """The ROS 2 bag (MCAP, version 9) of :func:`bag_columns`, one connection per topic in the order listed,
    written in bulk (lrfcal.io.mcap_write: the messages serialised as arrays, the file assembled from them).
    ``bulk`` False: :func:`bag_messages` serialised by one rosbags call each and written by rosbags' Writer, one
    call each (the same file, in several times the time: the reference tests/test_bulk_bags.py and
    benchmarks/bench_read.py compare with)."""
    if bulk:
        from lrfcal.io.mcap_write import BagTopic, write_rosbag2_mcap

        topics, messages, log_ns, channel, index = bag_columns(result, scenario)
        write_rosbag2_mcap(path, [BagTopic.humble(topic, typ) for topic, typ in topics], messages, log_ns, channel,
                           index)
        return
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = _typestore()

    topics, events = bag_messages(result, scenario)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=ts) for topic, msgtype in topics}
        for t_ns, topic, typ, msg in events:
            writer.write(conns[topic], t_ns, encode_cdr(msg) if typ == MULTIECHO_TYPE else ts.serialize_cdr(msg, typ))


def _stamps(t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROS times of simulation times ``t_s`` (M,) [s]: (ns, sec, nanosec) (M,) each, as :func:`_ns` rounds one."""
    ns = EPOCH_NS + np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)
    return ns, ns // 10**9, ns % 10**9


def _log_order(result: SimResult, scenario: Scenario, echoes: bool
               ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Every message's log time [ns], topic (0 scan, 1 joint state, 2 echoes) and index in its topic (M,) each, in
    log-time order: scans are logged at the end of the scan, on the recorder (servo) clock; with ``echoes`` scan
    k's MultiEchoLaserScan right after its LaserScan."""
    sensor = scenario.sensor
    scan_log, _, _ = _stamps((true_stamps(result, "scan") - scenario.servo.clock_offset_s) + sensor.scan_period_s)
    joint_log, _, _ = _stamps(true_stamps(result, "joint"))
    log = np.concatenate([scan_log, joint_log])
    kind = np.repeat([0, 1], [scan_log.size, joint_log.size])
    index = np.concatenate([np.arange(scan_log.size), np.arange(joint_log.size)])
    order = np.lexsort((index, kind, log))
    if echoes:  # each scan twice: its LaserScan, then its MultiEchoLaserScan
        order = np.repeat(order, np.where(kind[order] == 0, 2, 1))
        kind = kind[order]
        kind[1:][order[1:] == order[:-1]] = 2
        return log[order], kind, index[order]
    return log[order], kind[order], index[order]


def bag_columns(result: SimResult, scenario: Scenario) -> tuple[list[tuple[str, str]], list[Any],
                                                               NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The bag's topics [(topic, type)] (T,), their serialised messages (T,) and the file order (M,) x 3: message
    j is ``messages[topic[j]][index[j]]``, logged at ``log_ns[j]``, for lrfcal.io.mcap_write.write_rosbag2_mcap.
    The messages of :func:`bag_messages`, serialised in bulk (lrfcal.io.wire: the LaserScans and the JointStates
    each as one (messages, bytes) array; a MultiEchoLaserScan by lrfcal.io.multiecho, bytes each), the bytes
    rosbags' serialiser gives for each (tests/test_bulk_bags.py)."""
    from lrfcal.io.wire import encode_joint_states, encode_laserscans

    sensor, servo = scenario.sensor, scenario.servo
    floats = np.array(_scan_floats(result, scenario), dtype=np.float32)
    _, sec, nanosec = _stamps(result.scan_stamps_s)
    # float64 ranges and intensities rounded to float32 as they are written in (as astype rounds them)
    scans = encode_laserscans(sec, nanosec, LASER_FRAME, floats, result.ranges_m, result.intensities)
    j = result.joints
    _, sec, nanosec = _stamps(j.stamps_s)
    joints = encode_joint_states(sec, nanosec, "", (servo.joint,), j.positions_rad[:, None],
                                 j.velocities_rad_s[:, None], np.zeros((j.stamps_s.size, 0)))
    echoes = _echo_messages(result, scenario)
    topics = [(SCAN_TOPIC, LASERSCAN_TYPE), (JOINT_TOPIC, JOINTSTATE_TYPE)]
    messages: list[Any] = [scans, joints]
    if echoes is not None:
        topics.append((sensor.echoes.topic, MULTIECHO_TYPE))
        messages.append([encode_cdr(echoes(k)) for k in range(scans.shape[0])])
    return topics, messages, *_log_order(result, scenario, echoes is not None)


def _scan_floats(result: SimResult, scenario: Scenario) -> list[float]:
    """A LaserScan's float fields (lrfcal.io.wire.SCAN_FLOATS order) as float32 values: the LaserScans declare
    ``result.declared_angle_increment_rad`` when a fault set it, else the sensor's; angle_max is the true span."""
    sensor = scenario.sensor
    n = sensor.n_beams
    angle_max = sensor.angle_min_rad + (n - 1) * sensor.angle_increment_rad  # the true span, faults aside
    increment = (sensor.angle_increment_rad if result.declared_angle_increment_rad is None
                 else result.declared_angle_increment_rad)
    return [float(np.float32(v)) for v in (sensor.angle_min_rad, angle_max, increment, sensor.time_increment_s,
                                           sensor.scan_period_s, sensor.range_min_m, sensor.range_max_m)]


def _echo_messages(result: SimResult, scenario: Scenario) -> Callable[[int], MultiEchoScan] | None:
    """Scan k's MultiEchoLaserScan (None without echoes): per beam a LaserEcho with the beam's valid echoes, nearest
    first (none: empty), as urg_node fills it; its header and float fields those of scan k's LaserScan."""
    if result.echo_ranges_m is None or result.echo_intensities is None:
        return None
    er_all, ei_all = result.echo_ranges_m, result.echo_intensities
    floats = dict(zip(SCAN_FLOATS, _scan_floats(result, scenario), strict=True))
    _, sec, nanosec = _stamps(result.scan_stamps_s)

    def message(k: int) -> MultiEchoScan:
        ok = np.isfinite(er_all[k])
        header = Header(Stamp(int(sec[k]), int(nanosec[k])), LASER_FRAME)
        return MultiEchoScan(header=header, ranges=Echoes.of_rows(er_all[k], ok),
                             intensities=Echoes.of_rows(ei_all[k], ok), **floats)

    return message


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def bag_messages(result: SimResult, scenario: Scenario
                 ) -> tuple[list[tuple[str, str]], list[tuple[int, str, str, Any]]]:
    """The bag's topics [(topic, type)] and its messages [(log time ns, topic, type, message)] in log-time order:
    /scan and /joint_states; the LaserScans declare ``result.declared_angle_increment_rad`` when a fault set it,
    else the sensor's; with echoes (``result.echo_ranges_m``) also a MultiEchoLaserScan per scan on
    ``sensor.echoes.topic``, logged with its /scan: per beam a LaserEcho with the beam's valid echoes, nearest first
    (none: empty), as urg_node fills it, as lrfcal.io.multiecho's MultiEchoScan (written by its encoder, a fortieth
    of rosbags' time). A message's float32 fields hold float32 values, as a reader decodes them."""
    ts = _typestore()
    LaserScan = ts.types[LASERSCAN_TYPE]
    JointState = ts.types[JOINTSTATE_TYPE]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    with_echoes = result.echo_ranges_m is not None and result.echo_intensities is not None
    sensor, servo = scenario.sensor, scenario.servo

    def header(t_s: float, frame: str) -> Any:
        ns = _ns(t_s)
        return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)

    def f32(v: float) -> float:
        return float(np.float32(v))

    n = sensor.n_beams
    angle_max = sensor.angle_min_rad + (n - 1) * sensor.angle_increment_rad  # the true span, faults aside
    increment = (sensor.angle_increment_rad if result.declared_angle_increment_rad is None
                 else result.declared_angle_increment_rad)
    ranges32 = result.ranges_m.astype(np.float32)
    intens32 = result.intensities.astype(np.float32)
    offset = servo.clock_offset_s
    # (log time ns, kind, index): scans are logged at the end of the scan, on the recorder (servo) clock
    order = [(_ns(float(t) - offset + sensor.scan_period_s), 0, k) for k, t in enumerate(true_stamps(result, "scan"))]
    order += [(_ns(float(t)), 1, k) for k, t in enumerate(true_stamps(result, "joint"))]
    order.sort()
    empty = np.zeros(0, dtype=np.float64)
    topics = [(SCAN_TOPIC, LASERSCAN_TYPE), (JOINT_TOPIC, JOINTSTATE_TYPE)]
    if with_echoes:
        topics.append((sensor.echoes.topic, MULTIECHO_TYPE))
    events: list[tuple[int, str, str, Any]] = []
    for log_ns, kind, k in order:
        if kind == 0:
            msg = LaserScan(
                header=header(float(result.scan_stamps_s[k]), LASER_FRAME),
                angle_min=f32(sensor.angle_min_rad), angle_max=f32(angle_max),
                angle_increment=f32(increment), time_increment=f32(sensor.time_increment_s),
                scan_time=f32(sensor.scan_period_s), range_min=f32(sensor.range_min_m),
                range_max=f32(sensor.range_max_m), ranges=ranges32[k], intensities=intens32[k])
            events.append((log_ns, SCAN_TOPIC, LASERSCAN_TYPE, msg))
            if with_echoes:
                assert result.echo_ranges_m is not None and result.echo_intensities is not None
                er = result.echo_ranges_m[k]
                ok = np.isfinite(er)
                echo = MultiEchoScan(
                    header=msg.header, angle_min=msg.angle_min, angle_max=msg.angle_max,
                    angle_increment=msg.angle_increment, time_increment=msg.time_increment,
                    scan_time=msg.scan_time, range_min=msg.range_min, range_max=msg.range_max,
                    ranges=Echoes.of_rows(er, ok), intensities=Echoes.of_rows(result.echo_intensities[k], ok))
                events.append((log_ns, sensor.echoes.topic, MULTIECHO_TYPE, echo))
        else:
            j = result.joints
            msg = JointState(header=header(float(j.stamps_s[k]), ""), name=[servo.joint],
                             position=np.array([j.positions_rad[k]]),
                             velocity=np.array([j.velocities_rad_s[k]]), effort=empty)
            events.append((log_ns, JOINT_TOPIC, JOINTSTATE_TYPE, msg))
    return topics, events


def in_memory_bag(result: SimResult, scenario: Scenario) -> BagReader:
    """A bag reader for lrfcal.io.recording.read_recording (its ``bag_reader``) that hands :func:`bag_messages` to
    the bag reader's decoding (lrfcal.io.bag.bag_data) without writing or parsing a file: the Scans, JointStates
    and report of the bag :func:`write_bag` writes, in a fraction of the time (tests/test_recording.py). For
    studies, whose trials need the estimate, not the file."""
    from lrfcal.errors import InputError
    from lrfcal.io.bag import Topic, bag_data
    from lrfcal.io.bag_messages import ns_to_s

    topics, events = bag_messages(result, scenario)
    types = dict(topics)

    def topic(name: str) -> Topic:
        chosen = [(ns_to_s(t), m) for t, topic, _, m in events if topic == name]
        return Topic(np.array([t for t, _ in chosen], dtype=np.float64), [m for _, m in chosen],
                     topics=[name] * len(chosen))

    def read(scan: ScanSource, servo: ServoSource, warn: Callable[[str], None] | None) -> BagData:
        if scan.topic not in types or servo.topic not in types or servo.tf is not None or servo.stamp == "scan":
            raise InputError(f"simulated bag: topics {scan.topic} and {servo.topic} expected (it has "
                             f"{', '.join(types)})")
        assert servo.topic is not None
        return bag_data("simulated bag", topic(scan.topic), topic(servo.topic), types[scan.topic],
                        types[servo.topic], scan, servo, warn)

    return read


def distances_csv(result: SimResult) -> str:
    """distances.csv: header ``marker_i,marker_j,distance_m``, one row per measured pair (0.1 um)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["marker_i", "marker_j", "distance_m"])
    ids = result.tape.marker_ids
    for (i, j), d in zip(result.tape.pairs.tolist(), result.tape.distances_m.tolist(), strict=True):
        w.writerow([ids[i], ids[j], f"{d:.7f}"])
    return buf.getvalue()


def _dump(data: dict[str, Any]) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None)


def nominal_yaml(scenario: Scenario, marker_radius_m: float | None, range_sigma_m: float | None = None) -> str:
    """nominal.yaml (the rig file, docs/formats.md) from the scenario's design values (rig.nominal_dh,
    rig.nominal_mount) and where this bag keeps the scans and the joint; ``marker_radius_m`` (and the sensor's
    ``beam_divergence_rad``, which the marker model uses) only with markers (None: the key is left out);
    ``range_sigma_m``: the scanner's declared range noise (None: left out). A step-and-scan servo (``servo.mode:
    step``) is declared ``servo.motion: step``: every beam of a scan takes the angle at its scan's stamp. A scanner
    whose ranges wiggle along the scan (``sensor.systematic.beam_wiggle_m``, the URG-04LX's) is declared
    ``range_pattern: true``, as its user's rig file would (docs/real-data.md). The stand's parts (``rig.stand``) are
    declared as ``self_boxes``, as built (their user has the drawing); the design DH values' 1-sigma
    (``rig.nominal_dh_tolerance``) as ``dh_tolerance``."""
    rig = scenario.rig
    radius = {} if marker_radius_m is None else {"marker_radius_m": float(marker_radius_m),
                                                  "beam_divergence_rad": float(scenario.sensor.divergence_rad)}
    noise = {} if range_sigma_m is None else {"range_sigma_m": float(round(range_sigma_m, 9))}
    return _dump({
        "dh": rig.nominal_dh.to_dh().as_dict(),
        **({"dh_tolerance": rig.nominal_dh_tolerance.model_dump()} if rig.nominal_dh_tolerance is not None else {}),
        "mount": rig.nominal_mount.to_pose().as_dict(),
        **radius,
        **noise,
        **({"range_pattern": True} if scenario.sensor.systematic.beam_wiggle_m != 0.0 else {}),
        **({"self_boxes": [{"pose": part.pose.to_pose().as_dict(),
                            "size_m": [part.size_x_m, part.size_y_m, part.size_z_m]} for part in rig.stand]}
           if rig.stand else {}),
        "scan": {"topic": SCAN_TOPIC, "stamp": "header"},
        "servo": {"topic": JOINT_TOPIC, "joint": scenario.servo.joint, "unit": "rad", "stamp": "header",
                  **({"motion": "step"} if scenario.servo.mode == "step" else {})},
    })


def ground_truth_yaml(result: SimResult) -> str:
    """ground_truth.yaml: true DH and mount, marker centres ({} without markers), radius (null without markers),
    clock offset, tunnel dimensions, and the faults injected (lrfsim.simulation.faults; {} when none); ``systematic``
    (lrfsim.simulation.simulate.systematic_truth) only when a systematic range error is on."""
    t = result.truth
    extra = {"systematic": t.systematic} if t.systematic else {}
    return _dump({
        "dh": t.dh.as_dict(),
        "mount": t.mount.as_dict(),
        "markers": {mid: [float(v) for v in p] for mid, p in zip(t.marker_ids, t.markers_W, strict=True)},
        "marker_radius_m": None if t.marker_radius_m is None else float(t.marker_radius_m),
        "clock_offset_s": float(t.clock_offset_s),
        "tunnel": {k: float(v) for k, v in t.tunnel.items()} if t.tunnel is not None else None,
        "faults": result.faults,
        **extra,
    })


__all__ = ["EPOCH_NS", "JOINT_TOPIC", "MULTIECHO_TYPE", "SCAN_TOPIC", "bag_columns", "bag_messages", "check_output",
           "distances_csv", "ground_truth_yaml", "in_memory_bag", "nominal_yaml", "write_bag", "write_recording"]
