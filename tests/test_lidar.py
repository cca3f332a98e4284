"""The simulated Hokuyo: exact geometry without noise, noise spread, intensity model, dropouts, per-beam poses."""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrfcal.errors import InputError
from lrfcal.model.kinematics import beam_rays_M, transform_points
from lrfsim.cast import scans
from lrfsim.scenario.file import Scenario, parse_scenario
from lrfsim.sensors import lidar
from lrfsim.sensors.servo import sweep_trajectory
from lrfsim.world.scene import build_scene, laser_pose_W

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"


def _deep_update(base: dict, upd: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in upd.items():
        out[k] = _deep_update(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def small_scenario(markers: dict | None = None, **sections: dict) -> Scenario:
    """tunnel_v with a narrow sweep (+0.1 -> -0.1 rad, one pass: about 60 scans), updated by ``sections``
    (merged) and ``markers`` (replaced)."""
    data = yaml.safe_load((SCENARIOS / "tunnel_v.yaml").read_text())
    data = _deep_update(data, {"servo": {"start_rad": 0.1, "end_rad": -0.1, "passes": 1, "settle_s": 0.1}})
    data = _deep_update(data, sections)
    if markers is not None:
        data["markers"] = markers
    return parse_scenario(data, "test")


EXACT = {"sensor": {"noise": False, "footprint_rays": 1, "quantisation_m": 0.0}}


def _run(sc: Scenario, scene=None, seed: int = 0, phase_s: float = 0.0):
    scene = scene if scene is not None else build_scene(sc)
    traj = sweep_trajectory(sc.servo)
    starts = lidar.scan_start_times(traj.end_s, sc.sensor, phase_s)
    lam = traj.angle(lidar.beam_times(starts, sc.sensor))
    return scene, lam, scans.simulate_scans(scene, sc.sensor, lam, np.random.default_rng(seed))


def _exact_rays_W(sc: Scenario, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-beam origins and directions (S, N, 3) from lrfcal.model.kinematics with the true DH and mount."""
    mu = lidar.beam_angles(sc.sensor)
    o_M, d_M = beam_rays_M(lam, np.broadcast_to(mu, lam.shape), sc.rig.dh.to_dh())
    T = sc.rig.mount.to_pose().matrix()
    return transform_points(T, o_M), d_M @ T[:3, :3].T


def _tunnel_hits(sc: Scenario, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Analytic nearest hit on the tunnel's planes: range (S, N), cos(incidence), hit points (S, N, 3)."""
    t = sc.scene.tunnel
    planes = [((0, 1, 0), t.width_m / 2), ((0, -1, 0), t.width_m / 2), ((0, 0, -1), 0.0),
              ((0, 0, 1), t.height_m), ((1, 0, 0), t.plate_x_m), ((-1, 0, 0), -t.x_min_m)]
    best = np.full(o.shape[:-1], np.inf)
    cos = np.zeros(o.shape[:-1])
    for n, c in planes:
        n = np.array(n, dtype=float)
        dn = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (c - o @ n) / dn
        better = (dn > 1e-12) & (r > 0) & (r < best)
        best = np.where(better, r, best)
        cos = np.where(better, dn, cos)
    return best, cos, o + best[..., None] * d


def test_exact_planes_and_weak_dropouts() -> None:
    """Noise and footprint off: every wall/floor/ceiling/plate range equals the analytic ray-plane distance;
    returns below the detection threshold (far, grazing: a low gain makes many) drop out."""
    sc = small_scenario(sensor={**EXACT["sensor"], "intensity": {"gain_counts": 500.0}})
    scene, lam, out = _run(sc)
    o, d = _exact_rays_W(sc, lam)
    r_true, cos, p = _tunnel_hits(sc, o, d)
    t = sc.scene.tunnel
    mh = t.manhole
    near_marker = np.min(np.linalg.norm(p[..., None, :] - scene.markers_W, axis=-1), axis=-1) < 0.02
    on_plate = np.abs(p[..., 0] - t.plate_x_m) < 1e-9
    in_hole = on_plate & (np.abs(p[..., 1] - mh.center_y_m) < mh.width_m / 2 + 0.01) \
        & (np.abs(p[..., 2] - mh.center_z_m) < mh.height_m / 2 + 0.01)
    behind = p[..., 0] < t.x_min_m + 1e-6  # the open end is closed by nothing in the scene
    eligible = ~near_marker & ~in_hole & ~behind & np.isfinite(r_true)
    cfg = sc.sensor.intensity
    expected_P = cfg.gain_counts * sc.scene.materials.painted_steel * cos * (cfg.ref_range_m / r_true) ** 2
    strong = eligible & (expected_P > 1.2 * cfg.min_detectable_counts)
    weak = eligible & (expected_P < 0.8 * cfg.min_detectable_counts)
    assert strong.sum() > 20000
    assert np.all(np.isfinite(out.ranges_m[strong]))
    err = np.abs(out.ranges_m[strong] - r_true[strong])
    assert err.max() < 1e-6, err.max()
    # weak returns (far, grazing walls) drop out
    assert weak.sum() > 100
    assert np.all(np.isnan(out.ranges_m[weak]))
    # batching stays within its bound
    assert 0 < out.max_origin_error_m < 1e-6


def test_beam_poses_match_kinematics_and_move_within_a_scan() -> None:
    sc = small_scenario(**EXACT)
    scene = build_scene(sc)
    traj = sweep_trajectory(sc.servo)
    starts = lidar.scan_start_times(traj.end_s, sc.sensor)
    lam = traj.angle(lidar.beam_times(starts, sc.sensor))
    origins, R = lidar.beam_poses_W(scene, lam)
    o_ref, d_ref = _exact_rays_W(sc, lam)
    mu = lidar.beam_angles(sc.sensor)
    d = np.einsum("sbij,bj->sbi", R, np.stack([np.cos(mu), np.sin(mu), np.zeros_like(mu)], -1))
    assert np.abs(origins - o_ref).max() < 1e-12
    assert np.abs(d - d_ref).max() < 1e-12
    # while the servo moves, the first and last beam of a scan come from different poses
    moving = np.abs(lam[:, -1] - lam[:, 0]) > 1e-4
    assert moving.sum() > 10
    s = int(np.flatnonzero(moving)[len(np.flatnonzero(moving)) // 2])
    assert np.linalg.norm(origins[s, -1] - origins[s, 0]) > 1e-6
    assert np.abs(R[s, -1] - R[s, 0]).max() > 1e-4
    # and the hinge rotation matches MuJoCo's own kinematics at the beam's angle
    T = laser_pose_W(scene, float(lam[s, -1]))
    assert np.abs(T[:3, 3] - origins[s, -1]).max() < 1e-12
    assert np.abs(T[:3, :3] - R[s, -1]).max() < 1e-12
    # the sub-ray directions of the chunks are exact per beam
    ch = next(scans.iter_ray_chunks(scene, sc.sensor, lam[:4]))
    assert np.abs(ch.directions.reshape(4, -1, 3) - d_ref[:4]).max() < 1e-12


def _marker_on_beam(beam: int, distance_m: float, footprint: int) -> tuple[Scenario, np.ndarray]:
    """A scenario whose only marker sits on beam ``beam`` at ``distance_m`` while the servo rests at start."""
    base = small_scenario(**EXACT)
    mu = lidar.beam_angles(base.sensor)[beam]
    o, dvec = beam_rays_M(np.array([base.servo.start_rad]), np.array([mu]), base.rig.dh.to_dh())
    T = base.rig.mount.to_pose().matrix()
    centre = transform_points(T, o + distance_m * dvec)[0]
    sc = small_scenario(sensor={"noise": False, "footprint_rays": footprint, "quantisation_m": 0.0},
                        servo={"settle_s": 0.3},
                        markers={"radius_m": 0.005, "layout": {"kind": "points", "positions": [centre.tolist()]}})
    return sc, centre


@pytest.mark.parametrize("footprint", [1, 7])
def test_marker_centre_ray_and_intensity(footprint: int) -> None:
    """A ray through a marker's centre returns centre distance minus radius; markers outshine steel 10x."""
    beam, D = 560, 1.0
    sc, _ = _marker_on_beam(beam, D, footprint)
    scene, lam, out = _run(sc)
    still = np.all(lam == sc.servo.start_rad, axis=1)  # scans in the initial standstill
    assert still.sum() >= 5
    r = out.ranges_m[still, beam]
    # ring sub-rays (offset rho D from the centre) meet the sphere up to R - sqrt(R^2 - (rho D)^2) further out
    off = lidar.ring_half_angle(sc.sensor) * D
    tol = 1e-9 + 0.005 - math.sqrt(0.005**2 - off**2)
    assert np.all(np.abs(r - (D - 0.005)) <= tol), r
    if footprint > 1:
        assert np.all(r > D - 0.005 + 0.3 * tol)  # ... and do move the mixture
    marker_I = out.intensities[still, beam]
    # painted steel returns at the same range (within 5 %)
    rng_ok = np.isfinite(out.ranges_m) & (np.abs(out.ranges_m - (D - 0.005)) < 0.05)
    rng_ok[:, beam - 3:beam + 4] = False
    steel_I = out.intensities[rng_ok]
    assert steel_I.size > 10
    assert marker_I.min() >= 10 * steel_I.max()


def test_footprint_mixes_ranges_at_edges() -> None:
    """With a footprint, beams straddling the marker's edge return ranges between marker and wall."""
    beam, D = 560, 1.0
    sc, _ = _marker_on_beam(beam, D, 7)
    sc = parse_scenario(_deep_update(sc.model_dump(mode="json"), {"sensor": {"divergence_rad": 0.02}}), "t")
    scene, lam, out = _run(sc)
    still = np.all(lam == sc.servo.start_rad, axis=1)
    row = out.ranges_m[np.flatnonzero(still)[0]]
    wall = row[beam + 6]
    edge = row[beam - 5:beam + 6]
    assert np.any((edge > D - 0.005 + 1e-3) & (edge < wall - 1e-3))  # mixed pixels exist


def test_range_noise_spread() -> None:
    """Noise on: range errors have the configured sigma (10 mm below 10 m) within 10 %."""
    sc_exact = small_scenario(sensor={"noise": False, "footprint_rays": 1, "quantisation_m": 0.0})
    sc_noisy = small_scenario(sensor={"noise": True, "footprint_rays": 1})
    scene, lam, exact = _run(sc_exact)
    _, _, noisy = _run(sc_noisy, scene=scene, seed=3)
    both = np.isfinite(exact.ranges_m) & np.isfinite(noisy.ranges_m) & (exact.ranges_m < 10.0)
    err = (noisy.ranges_m - exact.ranges_m)[both]
    assert err.size > 20000
    assert abs(err.std() - 0.010) < 0.001
    assert abs(err.mean()) < 0.001
    q = noisy.ranges_m[both] / 0.001  # quantised to 1 mm
    assert np.abs(q - np.round(q)).max() < 1e-6


def test_range_sigma_bands_and_no_return_inf() -> None:
    sensor = small_scenario().sensor
    s = lidar.range_sigma(np.array([0.5, 9.99, 10.0, 10.01, 29.0, 45.0, 100.0]), sensor)
    assert np.allclose(s, [0.01, 0.01, 0.01, 0.03, 0.03, 0.05, 0.05])
    sc = small_scenario(sensor={"no_return": "inf", "noise": False})
    _, _, out = _run(sc)
    assert not np.isnan(out.ranges_m).any()
    assert np.isinf(out.ranges_m).any()


def test_typical_range_sigma_is_the_median_of_each_ranges_sigma() -> None:
    """typical_range_sigma, counted band by band, is np.median of range_sigma over the finite ranges to the bit:
    bands in any order, sigmas repeated, ranges on the bands' edges, NaN and +-inf, odd and even counts, none."""
    from lrfsim.scenario.sections import NoiseBand

    base = small_scenario().sensor
    rng = np.random.default_rng(11)
    values = [0.5, 1.0, 2.0, 3.0, 5.0, 7.0, 10.0, 40.0, np.nan, np.inf, -np.inf]
    checked = 0
    for _ in range(400):
        ups = rng.choice([1.0, 2.0, 5.0, 10.0, 30.0], size=int(rng.integers(1, 5)), replace=False)
        sigmas = rng.choice([0.01, 0.02, 0.03, 0.011], size=ups.size)
        sensor = base.model_copy(update={"noise_bands": tuple(
            NoiseBand(up_to_m=float(u), sigma_m=float(s)) for u, s in zip(ups, sigmas, strict=True))})
        r = rng.choice(values, size=int(rng.integers(0, 12)))
        finite = r[np.isfinite(r)]
        want = float(np.median(lidar.range_sigma(finite, sensor))) if finite.size else None
        assert lidar.typical_range_sigma(r, sensor) == want, (ups, sigmas, r)
        checked += want is not None
    assert checked > 300
    assert lidar.typical_range_sigma(np.ones(3), base.model_copy(update={"noise": False})) is None


def test_footprint_geometry() -> None:
    sensor = small_scenario(sensor={"footprint_rays": 7, "divergence_rad": 0.004}).sensor
    d = lidar.footprint_directions_L(sensor)
    assert d.shape == (1081, 7, 3)
    assert np.allclose(np.linalg.norm(d, axis=-1), 1.0)
    ang = np.arccos(np.clip(np.einsum("bfk,bk->bf", d, d[:, 0]), -1, 1))
    assert np.allclose(ang[:, 1:], lidar.ring_half_angle(sensor))
    assert 0.5 * 0.002 < lidar.ring_half_angle(sensor) < 0.002
    assert math.isclose(lidar.beam_angles(sensor)[540], 0.0, abs_tol=1e-12)


@pytest.mark.parametrize("footprint", ["edges", "full"])
def test_cast_on_threads_is_byte_identical(footprint: str) -> None:
    """The cast in 1, 2 and 3 threads (chunks of 4 scans, so the threads interleave): the same bytes, echoes too,
    and the progress callback sees every chunk in scan order; with either footprint cast."""
    sc = small_scenario(sensor={"echoes": {"enabled": True}})
    scene = build_scene(sc)
    traj = sweep_trajectory(sc.servo)
    lam = traj.angle(lidar.beam_times(lidar.scan_start_times(traj.end_s, sc.sensor, 0.004), sc.sensor))
    seen: list[int] = []
    one = scans.cast_scans(scene, sc.sensor, lam, chunk_scans=4, threads=1, footprint=footprint)
    for n in (2, 3):
        seen.clear()
        many = scans.cast_scans(scene, sc.sensor, lam, chunk_scans=4, threads=n, footprint=footprint,
                                  progress=lambda done, total: seen.append(done))
        for a, b in ((one.ranges_m, many.ranges_m), (one.intensities, many.intensities),
                     (one.echo_ranges_m, many.echo_ranges_m), (one.echo_power, many.echo_power)):
            assert a is not None and b is not None and a.tobytes() == b.tobytes()
        assert (many.n_rays, many.n_calls) == (one.n_rays, one.n_calls)
        assert many.max_parallax_correction_m == one.max_parallax_correction_m
        assert seen == [min(lam.shape[0], s + 4) for s in range(0, lam.shape[0], 4)]
    assert np.isfinite(one.ranges_m).mean() > 0.5  # the scans see the tunnel


def test_cast_threads_run_their_matrix_products_on_one_blas_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """The cast's chunks are its parallelism: inside them BLAS runs one thread (a BLAS thread per core in every
    chunk's products made 2 threads slower than 1 where the caller had not limited BLAS); the caller's limits are
    back after the cast."""
    from threadpoolctl import threadpool_info, threadpool_limits

    sc = small_scenario()
    scene = build_scene(sc)
    traj = sweep_trajectory(sc.servo)
    lam = traj.angle(lidar.beam_times(lidar.scan_start_times(traj.end_s, sc.sensor, 0.004), sc.sensor))
    seen: list[int] = []

    def watched(cast: Callable[..., object]) -> Callable[..., object]:
        def call(*args: object) -> object:
            seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
            return cast(*args)
        return call

    for name in ("cast_chunk", "cast_chunk_edges"):  # footprint_cast full and edges (the default)
        monkeypatch.setattr(scans, name, watched(getattr(scans, name)))
    with threadpool_limits(limits=2, user_api="blas"):
        scans.cast_scans(scene, sc.sensor, lam, chunk_scans=4, threads=2)
        after = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    assert seen and set(seen) == {1}
    assert after and set(after) == {2}


@pytest.mark.parametrize("divergence", [0.0003, 0.004, 0.02])
def test_edges_footprint_is_the_full_cast_where_it_matters(divergence: float) -> None:
    """The default cast (footprint "edges": the ring only at edges and near markers, elsewhere the centre ray's
    tangent plane) gives the full cast's ranges and intensities: bit-close on planes, the same on the marker and
    its mixed edge pixels, with chunks of 4 scans (so edges cross chunk borders) and a fraction of the rays; a ring
    wider than the angle between beams (0.02 rad) casts every sub-ray."""
    sc, _ = _marker_on_beam(560, 1.0, 7)
    sc = parse_scenario(_deep_update(sc.model_dump(mode="json"), {"sensor": {"divergence_rad": divergence}}), "t")
    scene = build_scene(sc)
    traj = sweep_trajectory(sc.servo)
    lam = traj.angle(lidar.beam_times(lidar.scan_start_times(traj.end_s, sc.sensor, 0.004), sc.sensor))
    full = scans.cast_scans(scene, sc.sensor, lam, chunk_scans=4, footprint="full")
    edges = scans.cast_scans(scene, sc.sensor, lam, chunk_scans=4)  # the default: sensor.footprint_cast
    assert np.array_equal(np.isfinite(full.ranges_m), np.isfinite(edges.ranges_m))
    hit = np.isfinite(full.ranges_m)
    dr = np.abs(full.ranges_m - edges.ranges_m)[hit]
    di = np.abs(full.intensities - edges.intensities)[hit] / full.intensities[hit]
    # on this scene not a beam differs (without the edge test 3 and 126 beams do, without the markers' 0 and 3)
    assert np.sum(dr > 1e-9) == 0 and np.sum(di > 1e-9) == 0, (np.sum(dr > 1e-9), np.sum(di > 1e-9))
    bright = full.intensities > 10 * np.median(full.intensities[hit])  # the marker and its mixed pixels
    assert bright.sum() >= 5
    assert np.abs(full.ranges_m - edges.ranges_m)[bright].max() < 1e-9
    assert np.abs(full.intensities[bright] / edges.intensities[bright] - 1).max() < 1e-9
    if 2 * lidar.ring_half_angle(sc.sensor) < sc.sensor.angle_increment_rad:
        assert edges.n_rays < 0.35 * full.n_rays
    else:
        assert edges.n_rays == full.n_rays and edges.ranges_m.tobytes() == full.ranges_m.tobytes()
    with pytest.raises(InputError, match="footprint"):
        scans.cast_scans(scene, sc.sensor, lam[:2], footprint="centre")


def test_range_noise_correlated_along_the_beams() -> None:
    """sensor.noise_correlation rho: the range noise of beams k apart correlates as rho^k (an AR(1) process along
    the scan, as a real URG-04LX's, docs/real-data.md), with the noise bands' sigma unchanged; rho = 0 draws the
    same numbers as before."""
    from lrfsim.scenario.sections import SensorConfig

    S, N = 400, 500
    cast = lidar.Cast(ranges_m=np.full((S, N), 5.0), intensities=np.full((S, N), 5000.0), n_rays=S * N, n_calls=1,
                      cast_time_s=0.0, total_time_s=0.0, max_origin_error_m=0.0, max_parallax_correction_m=0.0,
                      cutoff_m=60.0)
    plain = SensorConfig(quantisation_m=0.0)
    e0 = lidar.sensor_model(cast, plain, np.random.default_rng(7)).ranges_m - 5.0
    e7 = lidar.sensor_model(cast, plain.model_copy(update={"noise_correlation": 0.7}),
                            np.random.default_rng(7)).ranges_m - 5.0

    def corr(e: np.ndarray, k: int) -> float:
        return float(np.corrcoef(e[:, :-k].ravel(), e[:, k:].ravel())[0, 1])

    assert abs(e0.std() - 0.010) < 3e-4 and abs(e7.std() - 0.010) < 3e-4  # the band's 10 mm either way
    assert abs(corr(e0, 1)) < 0.02
    assert abs(corr(e7, 1) - 0.7) < 0.02 and abs(corr(e7, 2) - 0.49) < 0.02 and abs(corr(e7, 8) - 0.7**8) < 0.02
    np.testing.assert_array_equal(lidar.correlated_along_beams(e0, 0.0), e0)
