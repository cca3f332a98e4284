"""Simulator cost vs bare mj_multiRay, full-recording wall time, batching errors (scenario tunnel_v).

    taskset -c 0 /work/venv/bin/python benchmarks/bench_sim.py [SCENARIO]

1. bare: exactly the simulator's mj_multiRay calls (same origins, directions, counts, geomgroup, cutoff and
   output buffers), generated chunk by chunk outside the timer, timed around the call loop only;
2. sim: lrfsim.cast.scans.simulate_scans on the same motor angles (poses, rays, casts, sensor model), with every
   sub-ray cast (``sensor.footprint_cast: full``, the bare loop's rays) and with the default (``edges``);
3. recording: lrfsim.simulation.to_folder.simulate_to_folder (scene build, simulation, bag and side files);
4. batching: the largest distance between a call's shared origin and a beam's exact origin, and the largest
   angle between a cast direction and the exact beam direction, both against lrfcal.model.kinematics (eq. (3)).
Targets: sim / bare <= 1.5, recording < 5 s. Prints PASS/MISS per target (exit code 0 either way).

    /work/venv/bin/python benchmarks/bench_sim.py --peer [--repeats 5] [SCENARIO]

--peer: this project's cast against MuJoCo-LiDAR's CPU backend (``mujoco-lidar``, github.com/TATP-233/MuJoCo-LiDAR,
``MjLidarCPU.trace_rays``: one ``mj_multiRay`` call per pose, one thread) on the same rays of the same compiled MJCF
scene; installs nothing (``pip install 'lrf-calib[bench]'``). What is cast and timed: :func:`peer_main`; the
results: docs/speed.md.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from functools import partial
from pathlib import Path

import numpy as np

from lrfcal.model.kinematics import beam_rays_M, transform_points
from lrfsim.cast import scans
from lrfsim.scenario.file import Scenario, load_scenario
from lrfsim.scenario.sections import SensorConfig
from lrfsim.sensors import lidar
from lrfsim.sensors.servo import servo_trajectory
from lrfsim.simulation.to_folder import simulate_to_folder
from lrfsim.world.scene import Scene, build_scene

ROOT = Path(__file__).resolve().parents[1]


def main(path: Path) -> None:
    sc = load_scenario(path)
    scene = build_scene(sc)
    sensor = sc.sensor.model_copy(update={"footprint_cast": "full"})  # every sub-ray: the bare loop's rays
    traj = servo_trajectory(sc.servo)
    starts = lidar.scan_start_times(traj.end_s, sensor, 0.0)
    lam = traj.angle(lidar.beam_times(starts, sensor))
    N, F = sensor.n_beams, sensor.footprint_rays
    cutoff = scans.cast_cutoff_m(sensor)
    gg = np.ascontiguousarray(scene.lidar_geomgroup, dtype=np.uint8)
    m, d = scene.model, scene.data

    # exact per-beam rays from the kinematics (the reference for the batching errors)
    mu = np.broadcast_to(lidar.beam_angles(sensor), lam.shape)
    o_M, d_M = beam_rays_M(lam, mu, sc.rig.dh.to_dh())
    T = sc.rig.mount.to_pose().matrix()
    o_ref, d_ref = transform_points(T, o_M), d_M @ T[:3, :3].T

    # 1. bare mj_multiRay over the simulator's own calls
    M = 16 * N * F
    gid, dist, nrm = np.empty(M, np.int32), np.empty(M), np.empty((M, 3))
    bare_s, n_rays, n_calls = 0.0, 0, 0
    max_pos_err = max_dir_err = 0.0
    for ch in scans.iter_ray_chunks(scene, sensor, lam):
        t0 = time.perf_counter()
        scans.cast_chunk(m, d, gg, ch, cutoff, gid, dist, nrm)  # mj_multiRay over the chunk's calls, nothing else
        bare_s += time.perf_counter() - t0
        n_rays += ch.directions.shape[0]
        n_calls += len(ch.call_first)
        # batching errors against the kinematics: shared origin vs exact origin, centre direction vs exact
        sl = ch.scans
        exact_o = o_ref[sl]
        used_o = exact_o + ch.offset  # offset = shared origin - exact origin (from the simulator's own poses)
        max_pos_err = max(max_pos_err, float(np.linalg.norm(used_o - exact_o, axis=-1).max()))
        centre = ch.directions.reshape(sl.stop - sl.start, N, F, 3)[:, :, 0]
        # |d - d_ref| equals the angle between unit vectors to first order (arccos loses precision near 1)
        max_dir_err = max(max_dir_err, float(np.linalg.norm(centre - d_ref[sl], axis=-1).max()))
    # the shared origins themselves against the exact kinematic origins
    origins_W, _ = lidar.beam_poses_W(scene, lam)
    pose_err = float(np.abs(origins_W - o_ref).max())

    # 2. the simulator on the same angles
    out = scans.simulate_scans(scene, sensor, lam, np.random.default_rng(0))
    sim_s = out.total_time_s
    edges = scans.simulate_scans(scene, sc.sensor.model_copy(update={"footprint_cast": "edges"}), lam,
                                   np.random.default_rng(0))
    differ = int(np.sum(~((edges.ranges_m == out.ranges_m) | (np.isnan(edges.ranges_m) & np.isnan(out.ranges_m)))))

    # 3. a full recording
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        simulate_to_folder(sc, Path(tmp) / "rec")
        rec_s = time.perf_counter() - t0

    ratio = sim_s / bare_s
    rows = [
        ("scenario", f"{sc.name}: {lam.shape[0]} scans x {N} beams x {F} sub-rays", ""),
        ("rays", f"{n_rays:,} in {n_calls:,} mj_multiRay calls ({n_rays / n_calls:.0f} rays/call)", ""),
        ("bare mj_multiRay", f"{bare_s:.3f} s = {n_rays / bare_s / 1e6:.2f} Mrays/s", ""),
        ("simulator", f"{sim_s:.3f} s = {n_rays / sim_s / 1e6:.2f} Mrays/s (cast loop {out.cast_time_s:.3f} s)", ""),
        ("ratio sim / bare", f"{ratio:.2f} (target <= 1.5)", "PASS" if ratio <= 1.5 else "MISS"),
        ("simulator, footprint_cast edges", f"{edges.total_time_s:.3f} s = {edges.total_time_s / bare_s:.2f}x bare; "
         f"{differ} beams' ranges differ from the full cast's", ""),
        ("full recording", f"{rec_s:.2f} s (target < 5 s)", "PASS" if rec_s < 5.0 else "MISS"),
        ("batching origin error", f"{max_pos_err * 1e9:.0f} nm (target < 1000 nm)",
         "PASS" if max_pos_err < 1e-6 else "MISS"),
        ("batching direction error", f"{max_dir_err:.1e} rad (exact per beam)", ""),
        ("pose vs kinematics", f"{pose_err:.1e} m (MuJoCo hinge rotation vs eq. (3))", ""),
        ("parallax correction", f"largest {out.max_parallax_correction_m * 1e6:.2f} um applied", ""),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    for k, v, s in rows:
        print(f"{k:<{w0}}  {v:<{w1}}  {s}")


# --- --peer: this project's cast against MuJoCo-LiDAR's CPU backend -------------------------------------------

def _first_sweep(sc: Scenario) -> tuple[SensorConfig, np.ndarray]:
    """The centre rays' sensor (one sub-ray per beam, every ray cast) and the true motor angle at every beam (S, N)
    of the scans that lie wholly in the servo's first sweep (the trajectory's first move)."""
    sensor = sc.sensor.model_copy(update={"footprint_rays": 1, "footprint_cast": "full"})
    traj = servo_trajectory(sc.servo)
    k = 1 if traj.start_s.size > 1 else 0
    t0, t1 = float(traj.start_s[k]), float(traj.start_s[k] + traj.duration_s[k])
    starts = lidar.scan_start_times(traj.end_s, sensor, 0.0)
    last = (sensor.n_beams - 1) * sensor.time_increment_s
    sel = starts[(starts >= t0) & (starts + last <= t1)]
    return sensor, traj.angle(lidar.beam_times(sel, sensor))


def _our_calls(scene: Scene, sensor: SensorConfig, lam: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every mj_multiRay call of this project's cast of ``lam`` (S, N): (origin (3,), directions (n, 3)), copied."""
    calls = []
    for ch in scans.iter_ray_chunks(scene, sensor, lam):
        for o, a, n in zip(ch.call_origins, ch.call_first, ch.call_count, strict=True):
            calls.append((o.copy(), ch.directions[a:a + n].copy()))
    return calls


def _bare(scene: Scene, calls: list[tuple[np.ndarray, np.ndarray]], cutoff: float, record: bool = False
          ) -> tuple[np.ndarray, np.ndarray]:
    """mj_multiRay over ``calls`` in one thread: distances (M,) (NaN: no hit) and geom ids (M,)."""
    import mujoco

    M = sum(d.shape[0] for _, d in calls)
    gid, dist = np.empty(M, np.int32), np.empty(M)
    gg = np.ascontiguousarray(scene.lidar_geomgroup, dtype=np.uint8)
    i = 0
    for o, dirs in calls:
        n = dirs.shape[0]
        mujoco.mj_multiRay(scene.model, scene.data, o, dirs.reshape(-1), gg, 1, -1, gid[i:i + n], dist[i:i + n],
                           None, n, cutoff)
        i += n
    dist[gid < 0] = np.nan
    return dist, gid


class _GeomRecorder:
    """Stands in for the ``mujoco`` module inside MuJoCo-LiDAR's CPU backend during the untimed check: the same
    ``mj_multiRay``, and a copy of each call's geom ids (the backend keeps them to itself)."""

    def __init__(self) -> None:
        import mujoco

        self._mujoco = mujoco
        self.geomids: list[np.ndarray] = []

    def mj_multiRay(self, **kw: object) -> None:  # noqa: N802 (mujoco's name)
        self._mujoco.mj_multiRay(**kw)
        self.geomids.append(np.array(kw["geomid"], copy=True))


def _peer_jobs(scene: Scene, sensor: SensorConfig, lam: np.ndarray, per_scan: bool) -> list[tuple]:
    """The peer's calls ``trace_rays(pose_4x4, theta, phi)`` for the same rays as :func:`_our_calls`.

    ``per_scan``: the scan's motor angle (every beam at the middle beam's) is set in MuJoCo and the pose read from the
    laser site inside the timed loop, and the rays are the beam bearings in the laser frame (theta = mu, phi = 0), as
    the peer's users cast a 2D lidar; else one call per run of beams sharing an origin (this project's batching):
    pose [I | origin] and each ray's world direction as (theta, phi), prepared outside the timer."""
    if per_scan:
        mu = lidar.beam_angles(sensor)
        return [(float(q), mu, np.zeros_like(mu)) for q in lam[:, lam.shape[1] // 2].tolist()]
    jobs = []
    for o, dirs in _our_calls(scene, sensor, lam):
        T = np.eye(4)
        T[:3, 3] = o
        jobs.append((T, np.arctan2(dirs[:, 1], dirs[:, 0]), np.arcsin(np.clip(dirs[:, 2], -1.0, 1.0))))
    return jobs


def _peer_run(scene: Scene, lidar_cpu: object, jobs: list[tuple], M: int) -> np.ndarray:
    """The peer's cast of ``jobs`` (:func:`_peer_jobs`) in order: distances (M,), -1 for no hit."""
    import mujoco

    m, d = scene.model, scene.data
    out = np.empty(M)
    T = np.eye(4)
    i = 0
    for pose, theta, phi in jobs:
        if isinstance(pose, float):  # the scan's pose from MuJoCo's kinematics, as the peer's users read it
            d.qpos[scene.joint_qpos_adr] = pose
            mujoco.mj_kinematics(m, d)
            T[:3, 3] = d.site_xpos[scene.site_id]
            T[:3, :3] = d.site_xmat[scene.site_id].reshape(3, 3)
            pose = T
        lidar_cpu.trace_rays(pose, theta, phi)  # type: ignore[attr-defined]
        n = theta.shape[0]
        out[i:i + n] = lidar_cpu.get_distances()  # type: ignore[attr-defined]
        i += n
    return out


def _agreement(ours: np.ndarray, our_gid: np.ndarray, peer: np.ndarray, peer_gid: np.ndarray) -> str:
    """Where both casts hit the same geom: the largest range difference; and how many rays hit different geoms."""
    same = (our_gid == peer_gid) & (our_gid >= 0)
    diff = float(np.max(np.abs(ours[same] - peer[same]))) if same.any() else float("nan")
    other = int(np.sum(our_gid != peer_gid))
    return f"{int(same.sum()):,} rays on the same geom: max |dr| {diff:.1e} m; {other} rays on another geom or a miss"


def _peer_workload(name: str, scene: Scene, sensor: SensorConfig, lam: np.ndarray, per_scan: bool, repeats: int
                   ) -> None:
    """One workload of :func:`peer_main`: the untimed check that both casts hit the same geoms at the same ranges,
    then the four casts interleaved ``repeats`` times (a different order every repeat); prints their rows."""
    import mujoco
    from mujoco_lidar.core_cpu import MjLidarCPU, mjlidar_cpu

    S, N = lam.shape
    cutoff = scans.cast_cutoff_m(sensor)
    gg = np.ascontiguousarray(scene.lidar_geomgroup, dtype=np.uint8)
    calls = _our_calls(scene, sensor, lam)
    jobs = _peer_jobs(scene, sensor, lam, per_scan)
    peer = MjLidarCPU(scene.model, cutoff_dist=cutoff, geomgroup=gg, bodyexclude=-1)
    peer.update(scene.data)
    bare_r, bare_gid = _bare(scene, calls, cutoff)  # this cast's rays and hits (its geom ids: Cast has none)
    cast = scans.cast_scans(scene, sensor, lam, footprint="full")
    ours = cast.ranges_m.reshape(-1)
    rec = _GeomRecorder()
    mjlidar_cpu.mujoco = rec  # type: ignore[assignment]
    try:
        peer_r = _peer_run(scene, peer, jobs, S * N)
    finally:
        mjlidar_cpu.mujoco = mujoco
    peer_gid = np.concatenate(rec.geomids)
    threads = scans.default_threads()
    runs = {
        "MuJoCo-LiDAR MjLidarCPU": partial(_peer_run, scene, peer, jobs, S * N),
        "this cast, 1 thread": partial(scans.cast_scans, scene, sensor, lam, footprint="full", threads=1),
        f"this cast, {threads} threads": partial(scans.cast_scans, scene, sensor, lam, footprint="full"),
        "bare mj_multiRay, 1 thread": partial(_bare, scene, calls, cutoff),
    }
    times: dict[str, list[float]] = {k: [] for k in runs}
    keys = list(runs)
    for r in range(repeats):
        for k in keys[r % len(keys):] + keys[:r % len(keys)]:
            t0 = time.perf_counter()
            runs[k]()
            times[k].append(time.perf_counter() - t0)
    print(f"\n{name}: {len(calls):,} mj_multiRay calls ({S * N / len(calls):.0f} rays/call)")
    print(f"  this cast vs the peer: {_agreement(ours, bare_gid, peer_r, peer_gid)}")
    print(f"  the peer vs bare:      {_agreement(peer_r, peer_gid, bare_r, bare_gid)}")
    print(f"  this cast's largest parallax correction (a beam's range from its own origin, not the call's): "
          f"{cast.max_parallax_correction_m:.1e} m")
    ref = np.array(times["MuJoCo-LiDAR MjLidarCPU"])
    w = max(len(k) for k in runs)
    for k, t in times.items():
        mr = S * N / np.array(t) / 1e6
        ratio = ref / np.array(t)  # per repeat: the peer's time over this one's (> 1: faster than the peer)
        print(f"  {k:<{w}}  {np.median(mr):6.2f} Mrays/s ({mr.min():.2f}-{mr.max():.2f})  "
              f"speed vs the peer {np.median(ratio):.2f}x ({ratio.min():.2f}-{ratio.max():.2f})")


def peer_main(path: Path, repeats: int) -> int:
    """--peer (module docstring): the first sweep's centre rays cast by this project (lrfsim.cast.scans.cast_scans,
    1 thread and the default threads), by MuJoCo-LiDAR's ``MjLidarCPU`` and by bare single-thread mj_multiRay, all
    interleaved ``repeats`` times; Mrays/s (median and range) and the ratio to the peer per repeat."""
    try:
        import mujoco_lidar
    except ImportError:
        print("mujoco-lidar is not installed: pip install 'lrf-calib[bench]' (or pip install mujoco-lidar)")
        return 2
    import mujoco

    from lrfcal.runtime.memory import apply_memory_policy
    from lrfcal.runtime.threads import apply_thread_policy

    apply_memory_policy()  # as the programs run (one BLAS thread: the cast's threads are its own)
    apply_thread_policy()
    sc = load_scenario(path)
    scene = build_scene(sc)
    sensor, lam_beam = _first_sweep(sc)
    S, N = lam_beam.shape
    print(f"{sc.name}: first sweep, {S} scans x {N} centre rays = {S * N:,} rays; mujoco {mujoco.__version__}, "
          f"mujoco-lidar {mujoco_lidar.__version__}, {scans.default_threads()} cast threads, {repeats} repeats")
    workloads = {  # name: (motor angles (S, N), the peer's calls one per scan?)
        "one pose per scan": (np.repeat(lam_beam[:, N // 2:N // 2 + 1], N, axis=1), True),
        "each beam at its own time (the simulator's rays)": (lam_beam, False),
    }
    for name, (lam, per_scan) in workloads.items():
        _peer_workload(name, scene, sensor, lam, per_scan, repeats)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("scenario", nargs="?", type=Path, default=ROOT / "scenarios" / "tunnel_v.yaml",
                        help="scenario YAML (default: scenarios/tunnel_v.yaml)")
    parser.add_argument("--peer", action="store_true",
                        help="cast against MuJoCo-LiDAR's CPU backend instead (needs mujoco-lidar installed)")
    parser.add_argument("--repeats", type=int, default=5, help="--peer: interleaved repeats (default 5)")
    args = parser.parse_args()
    if args.peer:
        raise SystemExit(peer_main(args.scenario, args.repeats))
    main(args.scenario)
