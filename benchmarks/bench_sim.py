"""Simulator cost vs bare mj_multiRay, full-recording wall time, batching errors (scenario tunnel_v).

    taskset -c 0 /work/venv/bin/python benchmarks/bench_sim.py [SCENARIO]

1. bare: exactly the simulator's mj_multiRay calls (same origins, directions, counts, geomgroup, cutoff and
   output buffers), generated chunk by chunk outside the timer, timed around the call loop only;
2. sim: lrfsim.raycast.simulate_scans on the same motor angles (poses, rays, casts, sensor model), with every
   sub-ray cast (``sensor.footprint_cast: full``, the bare loop's rays) and with the default (``edges``);
3. recording: lrfsim.simulate.simulate_to_folder (scene build, simulation, bag and side files);
4. batching: the largest distance between a call's shared origin and a beam's exact origin, and the largest
   angle between a cast direction and the exact beam direction, both against lrfcal.model.kinematics (eq. (3)).
Targets: sim / bare <= 1.5, recording < 5 s. Prints PASS/MISS per target (exit code 0 either way).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from lrfcal.model.kinematics import beam_rays_M, transform_points
from lrfsim import lidar, raycast
from lrfsim.scenario import load_scenario
from lrfsim.scene import build_scene
from lrfsim.servo import servo_trajectory
from lrfsim.simulate import simulate_to_folder

ROOT = Path(__file__).resolve().parents[1]


def main(path: Path) -> None:
    sc = load_scenario(path)
    scene = build_scene(sc)
    sensor = sc.sensor.model_copy(update={"footprint_cast": "full"})  # every sub-ray: the bare loop's rays
    traj = servo_trajectory(sc.servo)
    starts = lidar.scan_start_times(traj.end_s, sensor, 0.0)
    lam = traj.angle(lidar.beam_times(starts, sensor))
    N, F = sensor.n_beams, sensor.footprint_rays
    cutoff = raycast.cast_cutoff_m(sensor)
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
    for ch in raycast.iter_ray_chunks(scene, sensor, lam):
        t0 = time.perf_counter()
        raycast.cast_chunk(m, d, gg, ch, cutoff, gid, dist, nrm)  # mj_multiRay over the chunk's calls, nothing else
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
    out = raycast.simulate_scans(scene, sensor, lam, np.random.default_rng(0))
    sim_s = out.total_time_s
    edges = raycast.simulate_scans(scene, sc.sensor.model_copy(update={"footprint_cast": "edges"}), lam,
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


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("scenario", nargs="?", type=Path, default=ROOT / "scenarios" / "tunnel_v.yaml",
                        help="scenario YAML (default: scenarios/tunnel_v.yaml)")
    main(parser.parse_args().scenario)
