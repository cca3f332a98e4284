"""``lrfcal reproject``: every beam of a bag, at its own time and motor angle, into frame M; writers for
PLY (x, y, z, intensity, time, scan, beam per point), a ROS 2 bag of sensor_msgs/msg/PointCloud2 (one cloud per
sweep) and a rerun file. Needs no tape distances.

A sweep is a monotonic run of the motor angle (scans ordered by time; standstills continue the run).
Scans whose beams the servo samples do not cover (within one sample period) are not reprojected; they are
counted in :class:`BeamCloud`.

Array shapes: S scans, N beams, P points.
"""

from __future__ import annotations

import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.io.files import atomic_file, check_outputs, swapped_folder, write_bytes_atomic
from lrfcal.io.yamlfile import read_yaml
from lrfcal.model.kinematics import DH, points_M
from lrfcal.model.scanner import true_returns
from lrfcal.model.unknowns import BY_NAME, INTRINSICS, core_vector
from lrfcal.stages.timing import covered_scans, motor_angles, sweep_passes, without_quantisation
from lrfcal.types import JointStates, Scans

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
#: frame_id of the PointCloud2 messages (the motor frame M of eq. (3))
CLOUD_FRAME = "lrf_motor"
CLOUD_TOPIC = "/lrf_cloud"
POINTCLOUD2_TYPE = "sensor_msgs/msg/PointCloud2"
#: sensor_msgs/msg/PointField datatype constants (the message definition): UINT32 = 6, FLOAT32 = 7, FLOAT64 = 8
_PF_UINT32, _PF_FLOAT32, _PF_FLOAT64 = 6, 7, 8
#: one point of the PLY and the PointCloud2 (little-endian, 32 bytes)
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("time", "<f8"),
                        ("scan", "<u4"), ("beam", "<u4")])


@dataclass(frozen=True)
class BeamCloud:
    """Every valid return of the covered scans in frame M.

    points_M (P, 3) [m]; intensity (P,); times_s (P,) beam time (laser clock); scan, beam (P,) indices into
    Scans; lambda_rad (P,) motor angle at the beam's time; sweep (P,) sweep index; scan_sweep (S,) sweep of
    every scan (-1 for uncovered scans); n_scans_uncovered: scans skipped because the servo samples do not
    cover them.
    """

    points_M: FloatArray
    intensity: FloatArray
    times_s: FloatArray
    scan: IntArray
    beam: IntArray
    lambda_rad: FloatArray
    sweep: IntArray
    scan_sweep: IntArray
    n_scans_uncovered: int

    def __len__(self) -> int:
        return int(self.times_s.size)


def reproject_beams(
    scans: Scans,
    joints: JointStates,
    dh: DH,
    clock_offset_s: float = 0.0,
    *,
    intrinsics: Mapping[str, float] | None = None,
    chunk_scans: int = 512,
    progress: Callable[[int, int], None] | None = None,
) -> BeamCloud:
    """Reproject every valid return at its own beam time and motor angle into frame M.

    Args:
        scans: S scans (per-scan bearings and time increments); joints: the motor angle samples.
        dh: DH parameters (eq. (3)); clock_offset_s: t_servo = t_laser - clock_offset_s;
        intrinsics: the scanner's and servo's intrinsics by name (lrfcal.model.unknowns; a calibration's estimates,
            :func:`read_calibration_intrinsics`; the others at their start), applied to the ranges, bearings and
            motor angles as the model does (lrfcal.model.scanner, lrfcal.model.motor).
        chunk_scans: scans per vectorised chunk; progress(scans_done, S) is called after each chunk.
    Returns:
        BeamCloud in scan-major, beam-minor order.
    """
    S = scans.stamps_s.size
    th = core_vector(dh, intrinsics or {})
    joints = without_quantisation(joints, scans)  # the motor angles as the calibration interpolates them
    covered = covered_scans(scans, joints, clock_offset_s) if S else np.zeros(0, bool)
    mid_t = scans.stamps_s + 0.5 * np.maximum(scans.beam_counts - 1, 0) * scans.time_increment_s
    scan_sweep = np.full(S, -1, dtype=np.int64)
    if covered.any():
        lam_mid = motor_angles(mid_t[covered], joints, clock_offset_s)
        scan_sweep[covered] = sweep_passes(lam_mid, min_fraction=0.0, min_scans=1)
    parts: list[tuple[FloatArray, FloatArray, FloatArray, IntArray, IntArray, FloatArray]] = []
    for s0 in range(0, S, chunk_scans):
        sl = slice(s0, min(S, s0 + chunk_scans))
        r = scans.ranges_m[sl]
        ok = np.isfinite(r) & covered[sl, None]
        ss, bb = np.nonzero(ok)
        t = scans.stamps_s[sl][ss] + bb * scans.time_increment_s[sl][ss]  # the beam's own time (written out)
        q = motor_angles(scans.angle_times_at(ss + s0, bb), joints, clock_offset_s)
        r_true, lam, mu_true = true_returns(th, r[ss, bb], q, scans.mu_rad[sl][ss, bb])
        p = points_M(r_true, lam, mu_true, dh)
        parts.append((p, scans.intensities[sl][ss, bb], t, ss + s0, bb, lam))
        if progress is not None:
            progress(sl.stop, S)
    if parts:
        p, inten, t, ss, bb, lam = (np.concatenate(x) for x in zip(*parts, strict=True))
    else:
        p, inten, t, lam = np.zeros((0, 3)), np.zeros(0), np.zeros(0), np.zeros(0)
        ss = bb = np.zeros(0, dtype=np.int64)
    return BeamCloud(points_M=p, intensity=inten.astype(np.float64), times_s=t, scan=ss.astype(np.int64),
                     beam=bb.astype(np.int64), lambda_rad=lam, sweep=scan_sweep[ss], scan_sweep=scan_sweep,
                     n_scans_uncovered=int((~covered).sum()))


def point_records(cloud: BeamCloud, sel: Any = slice(None)) -> NDArray[Any]:
    """The points as a structured array of :data:`POINT_DTYPE` (``sel`` picks a subset)."""
    p = cloud.points_M[sel]
    out = np.empty(p.shape[0], dtype=POINT_DTYPE)
    out["x"], out["y"], out["z"] = p[:, 0], p[:, 1], p[:, 2]
    out["intensity"] = cloud.intensity[sel]
    out["time"] = cloud.times_s[sel]
    out["scan"] = cloud.scan[sel]
    out["beam"] = cloud.beam[sel]
    return out


# --- writers (atomic: a temporary sibling renamed into place) ------------------------------------------------

def write_cloud_ply(path: str | Path, cloud: BeamCloud) -> Path:
    """Binary little-endian PLY: float x, y, z [m], float intensity, double time [s, laser clock],
    uint scan, uint beam per point; written atomically."""
    rec = point_records(cloud)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment lrfcal reproject: frame M (motor frame), SI units\n"
        f"element vertex {rec.size}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float intensity\nproperty double time\nproperty uint scan\nproperty uint beam\nend_header\n"
    )
    return write_bytes_atomic(Path(path), [header.encode("ascii"), rec.data.cast("B")])


def read_cloud_ply(path: str | Path) -> NDArray[Any]:
    """Read a PLY written by :func:`write_cloud_ply` back as a :data:`POINT_DTYPE` array."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(data[end:], dtype=POINT_DTYPE)


def write_cloud_bag(path: str | Path, cloud: BeamCloud, frame_id: str = CLOUD_FRAME, topic: str = CLOUD_TOPIC
                    ) -> Path:
    """A ROS 2 bag (MCAP) with one sensor_msgs/msg/PointCloud2 per sweep on ``topic``: fields x, y, z,
    intensity (FLOAT32), time (FLOAT64, laser clock [s]), scan, beam (UINT32); header.stamp = the sweep's
    first beam time, logged at its last. Written into a temporary folder renamed into place."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    PC2 = ts.types[POINTCLOUD2_TYPE]
    PF = ts.types["sensor_msgs/msg/PointField"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    layout = POINT_DTYPE.fields
    assert layout is not None  # a structured dtype
    fields = [PF(name=n, offset=layout[n][1], datatype=d, count=1) for n, d in (
        ("x", _PF_FLOAT32), ("y", _PF_FLOAT32), ("z", _PF_FLOAT32), ("intensity", _PF_FLOAT32),
        ("time", _PF_FLOAT64), ("scan", _PF_UINT32), ("beam", _PF_UINT32))]
    # rosbags' Writer makes the bag folder and names its data file after it: swapped_folder names it out's name
    with swapped_folder(path, make=False) as tmp, Writer(tmp, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(topic, POINTCLOUD2_TYPE, typestore=ts)
        for sw in np.unique(cloud.sweep):
            sel = np.flatnonzero(cloud.sweep == sw)
            rec = point_records(cloud, sel)
            t0, t1 = float(cloud.times_s[sel].min()), float(cloud.times_s[sel].max())
            ns0 = int(round(t0 * 1e9))
            msg = PC2(header=Header(stamp=Time(sec=ns0 // 10**9, nanosec=ns0 % 10**9), frame_id=frame_id),
                      height=1, width=rec.size, fields=fields, is_bigendian=False,
                      point_step=POINT_DTYPE.itemsize, row_step=POINT_DTYPE.itemsize * rec.size,
                      data=np.frombuffer(rec.tobytes(), dtype=np.uint8), is_dense=True)
            w.write(conn, max(0, int(round(t1 * 1e9))), ts.serialize_cdr(msg, POINTCLOUD2_TYPE))
    return path


def write_cloud_rrd(path: str | Path, cloud: BeamCloud, max_points: int = 2_000_000) -> Path:
    """A rerun file: the cloud in ``world/M/cloud`` per sweep on the ``sweep`` timeline, coloured by
    intensity (at most ``max_points``, evenly subsampled); written atomically."""
    import rerun as rr

    from lrfcal.report.vizdata import intensity_colors, subsample_indices

    path = Path(path)
    keep = subsample_indices(len(cloud), max_points)
    rec = rr.RecordingStream("lrfcal_reproject", recording_id=str(uuid.uuid4()))
    with atomic_file(path) as tmp:
        rec.save(tmp)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        sweeps = cloud.sweep[keep]
        colors = intensity_colors(cloud.intensity[keep])
        for sw in np.unique(sweeps):
            sel = keep[sweeps == sw]
            rec.set_time("sweep", sequence=int(sw))
            rec.log("world/M/cloud", rr.Points3D(cloud.points_M[sel], colors=colors[sweeps == sw], radii=0.004))
        rec.flush()
        rec.disconnect()
    return path


# --- DH from calibration.yaml --------------------------------------------------------------------------------

def read_calibration_dh(path: str | Path) -> DH:
    """The DH parameters of a calibration.yaml (``dh: {a: {value, sigma}, ...}``; plain numbers accepted)."""
    path = Path(path)
    data = read_yaml(path, "calibration file")
    dh = data.get("dh") if isinstance(data, dict) else None
    if not isinstance(dh, dict):
        raise InputError(f"{path}: dh: missing (expected dh: {{a: {{value: ..., sigma: ...}}, ...}})")
    out = {}
    for n in ("a", "alpha", "b", "beta"):
        v = dh.get(n)
        v = v.get("value") if isinstance(v, dict) else v
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(f"{path}: dh.{n}.value: expected a finite number, got {v!r}")
        out[n] = float(v)
    return DH(**out)


def read_calibration_intrinsics(path: str | Path) -> dict[str, float]:
    """The intrinsics a calibration.yaml estimated, by name (``intrinsics: {name: {value, sigma, ...}}``; those held,
    sigma null, are left out: they are at their start). A file without ``intrinsics`` (an older calibration) gives
    its ``range_offset_m`` when that was estimated."""
    data = read_yaml(Path(path), "calibration file")
    section = data.get("intrinsics") if isinstance(data, dict) else None
    if section is None:
        entry = data.get("range_offset_m") if isinstance(data, dict) else None
        section = {"range_offset": entry} if isinstance(entry, dict) else {}
    if not isinstance(section, dict):
        raise InputError(f"{path}: intrinsics: expected a mapping of name: {{value, sigma}}, got {section!r}")
    out = {}
    for name, entry in section.items():
        if name not in INTRINSICS:
            raise InputError(f"{path}: intrinsics.{name}: not an intrinsic of the rig model (known: "
                             f"{', '.join(INTRINSICS)})")
        if not isinstance(entry, dict) or entry.get("sigma") is None:
            continue
        v = entry.get("value")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise InputError(f"{path}: intrinsics.{name}.value: expected a finite number "
                             f"({BY_NAME[name].unit}), got {v!r}")
        out[name] = float(v)
    return out


def read_calibration_clock_offset(path: str | Path) -> float | None:
    """The clock offset (laser stamp - servo stamp) [s] a calibration.yaml estimated or held
    (``clock_offset_s: {value, sigma}``), None when the file has none (older calibrations)."""
    data = read_yaml(Path(path), "calibration file")
    entry = data.get("clock_offset_s") if isinstance(data, dict) else None
    v = entry.get("value") if isinstance(entry, dict) else entry
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise InputError(f"{path}: clock_offset_s.value: expected a finite number of seconds, got {v!r}")
    return float(v)


# --- the command ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CloudOutputs:
    """The files :func:`reproject_bag` writes: the PLY, and optionally the rerun file and the PointCloud2 bag."""

    ply: str | Path
    rrd: str | Path | None = None
    bag: str | Path | None = None


def reproject_bag(
    bag: str | Path,
    nominal: str | Path | None,
    outputs: CloudOutputs,
    *,
    calibration: str | Path | None = None,
    clock_offset_s: float | None = None,
    options: dict[str, Any] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    warn: Callable[[str], None] | None = None,
) -> list[str]:
    """``lrfcal reproject``: read BAG as the rig file ``nominal`` says (None: the nominal.yaml of BAG, a recording
    folder, as `lrfcal calibrate` takes it; ``options``: lrfcal.io.rig.with_overrides keywords),
    reproject every beam with the calibration's DH (else the nominal) and its clock offset (``clock_offset_s``
    when given, else the calibration's estimate, else 0; on top of the reader's coarse offset), write the PLY
    (and the PointCloud2 bag, the rerun file). ``progress(stage, done, total)`` reports reading and
    reprojection. Returns summary lines.

    Raises:
        InputError: bad input, or an output path that overlaps an input.
    """
    from lrfcal.io.recording import RIG_FILE, read_recording
    from lrfcal.io.rig import with_overrides
    from lrfcal.io.saved_calibration import calibration_file
    from lrfcal.model.kinematics import refuse_placeholder_dh

    # a calibration folder stands for its calibration.yaml, as `lrfcal check` takes it
    calibration = calibration_file(calibration) if calibration is not None else None
    if nominal is None:  # a recording folder holds its rig file, as `lrfcal calibrate REC` reads it
        if not (Path(bag) / RIG_FILE).is_file():
            raise InputError(f"{bag}: no rig file: give --nominal YAML (a recording folder holds its {RIG_FILE}; "
                             f"`lrfcal inspect {bag} -o rig.yaml` writes one)")
        nominal = Path(bag) / RIG_FILE
    bag, nominal, out, rrd, bag_out = Path(bag), Path(nominal), Path(outputs.ply), outputs.rrd, outputs.bag
    outs = [Path(p) for p in (out, rrd, bag_out) if p is not None]
    check_outputs([p for p in (bag, nominal, calibration) if p is not None], outs)
    from lrfcal.io.recording import read_nominal

    nom = read_nominal(nominal)
    if calibration is None:  # the DH come from the rig file: not its placeholder
        refuse_placeholder_dh(nom.dh, str(nominal), "reprojecting (or give --calibration)")
    scan, servo = with_overrides(nom.scan, nom.servo, **(options or {}))

    def stage(name: str) -> Callable[[int, int], None] | None:
        return None if progress is None else (lambda d, t: progress(name, d, t))

    # a folder is read as `lrfcal calibrate` reads a recording folder (its bag/, else its one bag or scan log; a ROS 2
    # bag folder stays itself: read_recording resolves it); any other path is the bag, named as such when missing
    folder = bag if bag.is_dir() else None
    rec = read_recording(folder, bag=None if folder else bag, nominal=nominal, scan=scan, servo=servo,
                         require_distances=False, progress=stage("reading"), warn=warn,
                         give_bag="give the bag itself as BAG")
    dh = read_calibration_dh(calibration) if calibration is not None else rec.nominal.dh
    if clock_offset_s is not None:
        offset, offset_from = float(clock_offset_s), "given"
    else:
        found = read_calibration_clock_offset(calibration) if calibration is not None else None
        offset, offset_from = (0.0, "none") if found is None else (found, f"from {calibration}")
    intrinsics = read_calibration_intrinsics(calibration) if calibration is not None else {}
    cloud = reproject_beams(rec.scans, rec.joints, dh, offset, intrinsics=intrinsics, progress=stage("reprojecting"))
    lines = list(rec.report.lines()) if rec.report is not None else []
    n_sweeps = int(np.unique(cloud.sweep).size)
    lines.append(f"reprojected {len(cloud)} returns of {rec.scans.stamps_s.size - cloud.n_scans_uncovered} scans "
                 f"({cloud.n_scans_uncovered} not covered by the servo samples, skipped) in {n_sweeps} sweeps, "
                 f"DH from {calibration if calibration is not None else nominal} "
                 f"(a {dh.a:.4f} m, alpha {np.degrees(dh.alpha):.3f} deg, b {dh.b:.4f} m, beta "
                 f"{np.degrees(dh.beta):.3f} deg), fine clock offset {offset:+.6f} s ({offset_from})"
                 + "".join(f", {n} {v:+.6g}{'' if BY_NAME[n].unit == '1' else ' ' + BY_NAME[n].unit}"
                           for n, v in intrinsics.items() if n != "marker_range_bias"))  # a marker-return bias
    write_cloud_ply(out, cloud)
    lines.append(f"wrote {out}")
    if bag_out is not None:
        write_cloud_bag(bag_out, cloud)
        lines.append(f"wrote {bag_out} ({n_sweeps} PointCloud2 on {CLOUD_TOPIC}, frame {CLOUD_FRAME})")
    if rrd is not None:
        write_cloud_rrd(rrd, cloud)
        lines.append(f"wrote {rrd}")
    return lines


__all__ = ["BeamCloud", "CLOUD_FRAME", "CloudOutputs", "CLOUD_TOPIC", "POINT_DTYPE", "point_records",
           "read_calibration_clock_offset", "read_calibration_dh",
           "read_calibration_intrinsics", "read_cloud_ply", "reproject_bag", "reproject_beams",
           "write_cloud_bag", "write_cloud_ply", "write_cloud_rrd"]
