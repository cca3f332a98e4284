"""lrfcal.io.multiecho: MultiEchoLaserScan read and written with numpy gives what rosbags' own (de)serialisers give,
in both wire formats, for every header length (CDR's alignment) and echo count; a simulated recording's /echoes
are the bytes rosbags would write; big-endian CDR is left to rosbags."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore
from test_lidar import small_scenario

from lrfcal.io import multiecho
from lrfcal.io.bag_messages import decode_message
from lrfcal.io.multiecho import MULTIECHO_TYPE, Echoes, MultiEchoScan
from lrfsim.simulation.recording import bag_messages
from lrfsim.simulation.simulate import simulate

FLOATS = ("angle_min", "angle_max", "angle_increment", "time_increment", "scan_time", "range_min", "range_max")


def _message(ts, rng: np.random.Generator, frame: str, n_beams: int, ros1: bool, short_intensities: bool = False):
    """A rosbags MultiEchoLaserScan of random echoes: 0-3 per beam, with NaN, inf and 0 among them."""
    LE = ts.types["sensor_msgs/msg/LaserEcho"]
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    counts = rng.integers(0, 4, n_beams)
    pool = np.array([np.nan, np.inf, 0.0, 0.02, 31.5], dtype=np.float32)

    def echo(c: int) -> np.ndarray:
        v = rng.uniform(0.05, 30.0, c).astype(np.float32)
        odd = rng.random(c) < 0.2
        v[odd] = rng.choice(pool, int(odd.sum()))
        return v

    ranges = [LE(echoes=echo(c)) for c in counts]
    n_int = n_beams // 2 if short_intensities else n_beams
    intens = [LE(echoes=rng.uniform(0, 9000, c).astype(np.float32)) for c in counts[:n_int]]
    head = {"stamp": Time(sec=int(rng.integers(0, 2**31)), nanosec=int(rng.integers(0, 10**9))), "frame_id": frame}
    if ros1:
        head["seq"] = int(rng.integers(0, 2**32))
    floats = dict(zip(FLOATS, rng.normal(0, 3, 7).astype(np.float32).tolist(), strict=True))
    return ts.types[MULTIECHO_TYPE](header=Header(**head), ranges=ranges, intensities=intens, **floats)


def _same(got: MultiEchoScan, msg) -> None:
    assert got.header.frame_id == msg.header.frame_id
    assert (got.header.stamp.sec, got.header.stamp.nanosec) == (msg.header.stamp.sec, msg.header.stamp.nanosec)
    for f in FLOATS:
        assert getattr(got, f) == getattr(msg, f), f
    for mine, theirs in ((got.ranges, msg.ranges), (got.intensities, msg.intensities)):
        want = Echoes.of(theirs)
        assert len(mine) == len(theirs)
        assert np.array_equal(mine.counts, want.counts)
        assert np.array_equal(mine.values.view(np.uint32), want.values.view(np.uint32))  # bit for bit, NaN too


@pytest.mark.parametrize("store", [Stores.ROS2_HUMBLE, Stores.ROS1_NOETIC])
def test_decode_and_encode_as_rosbags_does(store: Stores) -> None:
    ts = get_typestore(store)
    ros1 = store == Stores.ROS1_NOETIC
    rng = np.random.default_rng(7)
    for frame in ("", "l", "la", "las", "laser", "base_laser_link"):  # every remainder of the header mod 4
        for n_beams, short in ((0, False), (1, False), (25, False), (1081, False), (40, True)):
            msg = _message(ts, rng, frame, n_beams, ros1, short)
            raw = bytes(ts.serialize_ros1(msg, MULTIECHO_TYPE) if ros1 else ts.serialize_cdr(msg, MULTIECHO_TYPE))
            got = multiecho.decode(raw, cdr=not ros1)
            _same(got, msg)
            if not ros1:
                assert multiecho.encode_cdr(got) == raw
    with pytest.raises(ValueError):
        multiecho.decode(raw + b"\x00\x00\x00\x00", cdr=not ros1)


def test_big_endian_cdr_is_left_to_rosbags() -> None:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    msg = _message(ts, np.random.default_rng(1), "laser", 30, ros1=False)
    raw = bytes(ts.serialize_cdr(msg, MULTIECHO_TYPE, little_endian=False))
    with pytest.raises(ValueError, match="not little endian"):
        multiecho.decode(raw, cdr=True)
    reader = SimpleNamespace(is2=True, deserialize=lambda r, t: ts.deserialize_cdr(r, t))
    back = decode_message(reader, raw, MULTIECHO_TYPE)
    assert not isinstance(back, MultiEchoScan)
    _same(multiecho.decode(bytes(ts.serialize_cdr(back, MULTIECHO_TYPE)), cdr=True), msg)


def test_simulated_echoes_are_the_bytes_rosbags_writes() -> None:
    """The simulator's /echoes, encoded here, against rosbags' serialiser of the same message built as LaserEcho
    objects (the beam's finite echoes, nearest first, as float32)."""
    sc = small_scenario(sensor={"echoes": {"enabled": True, "separation_m": 0.004}, "divergence_rad": 0.01})
    res = simulate(sc)
    _, events = bag_messages(res, sc)
    echoes = [m for _, _, t, m in events if t == MULTIECHO_TYPE]
    assert len(echoes) == res.ranges_m.shape[0]
    ts = get_typestore(Stores.ROS2_HUMBLE)
    LE = ts.types["sensor_msgs/msg/LaserEcho"]
    assert res.echo_ranges_m is not None and res.echo_intensities is not None
    n_split = 0
    for k in np.linspace(0, len(echoes) - 1, 12).astype(int):
        m = echoes[k]
        er, ei = res.echo_ranges_m[k].astype(np.float32), res.echo_intensities[k].astype(np.float32)
        ok = np.isfinite(er)
        n_split += int((ok.sum(1) >= 2).sum())
        built = ts.types[MULTIECHO_TYPE](
            header=m.header, **{f: getattr(m, f) for f in FLOATS},
            ranges=[LE(echoes=er[b][ok[b]]) for b in range(er.shape[0])],
            intensities=[LE(echoes=ei[b][ok[b]]) for b in range(er.shape[0])])
        assert multiecho.encode_cdr(m) == bytes(ts.serialize_cdr(built, MULTIECHO_TYPE))
    assert n_split > 0  # beams with two echoes were among those compared


def test_the_definitions_are_humbles() -> None:
    """multiecho.FIELDDEFS (what lrfcal.io.mcap_write names the type by, without loading Humble's store) are the
    definitions ROS 2 Humble's store holds."""
    humble = get_typestore(Stores.ROS2_HUMBLE).fielddefs
    assert set(multiecho.FIELDDEFS) == {MULTIECHO_TYPE, "sensor_msgs/msg/LaserEcho"}
    for name, defs in multiecho.FIELDDEFS.items():
        assert defs == humble[name], name
