"""One simulated recording: servo sweep, laser scans, joint states and tape, as arrays (no I/O: the recording
folder is written by lrfsim.simulation.recording; simulate and write in one call: lrfsim.simulation.to_folder).

Time: the true time is the servo clock, 0 at the start of the sweep. The laser runs free: its first scan
starts at a random phase in [0, scan_period) (seeded), and it stamps instants on its own clock,
laser = servo + clock_offset_s. Random streams are seeded from ``scenario.seed`` per purpose (laser phase,
sensor noise, tape), so changing one model does not reshuffle the others.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from lrfsim.cast.scans import cast_scans
from lrfsim.scenario.file import Scenario
from lrfsim.scenario.sections import SensorConfig
from lrfsim.sensors.lidar import Cast, beam_angles, beam_times, scan_start_times, sensor_model
from lrfsim.sensors.servo import check_trajectory, joint_samples, laser_time, servo_trajectory, step_scan_phase_s
from lrfsim.sensors.tape import measure_tape

from .result import SimResult, SimStats, SimTruth

if TYPE_CHECKING:
    from lrfsim.cast.forked import Forked
    from lrfsim.world.scene import Scene

FloatArray = NDArray[np.float64]

# purpose tags of the random streams: default_rng([seed, tag])
_RNG_PHASE, _RNG_SENSOR, _RNG_TAPE = 0x70686173, 0x6E6F6973, 0x74617065


def systematic_truth(sensor: SensorConfig) -> dict[str, float] | None:
    """The systematic range errors a calibration could be compared with (ground_truth.yaml ``systematic``):
    the non-zero ``sensor.systematic`` coefficients and, with an intensity bias, ``saturated_return_bias_m`` =
    k_I log10(saturation_counts / intensity_ref_counts), the bias of every saturated return (the markers at
    the tunnel's ranges). None when every effect is off."""
    c = sensor.systematic
    out = {k: float(v) for k, v in c.model_dump().items()
           if v != 0.0 and k in ("range_offset_m", "intensity_bias_m_per_decade", "incidence_bias_m",
                                 "drift_amplitude_m", "beam_wiggle_m", "range_wiggle_m")}
    if not out:
        return None
    if "intensity_bias_m_per_decade" in out:
        out["intensity_ref_counts"] = float(c.intensity_ref_counts)
        out["saturated_return_bias_m"] = float(c.intensity_bias_m_per_decade * np.log10(
            sensor.intensity.saturation_counts / c.intensity_ref_counts))
    if "drift_amplitude_m" in out:
        out["drift_time_constant_s"] = float(c.drift_time_constant_s)
        out["drift_elapsed_s"] = float(c.drift_elapsed_s)
    if "beam_wiggle_m" in out:
        out["beam_wiggle_period_beams"] = float(c.beam_wiggle_period_beams)
    if "range_wiggle_m" in out:
        out["range_wiggle_period_m"] = float(c.range_wiggle_period_m)
    return out


@dataclass(frozen=True)
class Geometry:
    """The noise-free part of a recording, cast once (:func:`cast_geometry`): the scene, the laser phase and scan
    start times (servo clock) it was cast with, the true motor angle of every beam (S, N) and the cast
    (lrfsim.sensors.lidar.Cast). Recordings that differ only in noise reuse it (:func:`simulate_from_geometry`)."""

    scenario_name: str
    scene: Scene
    phase_s: float
    starts_s: FloatArray
    beam_lambda_rad: FloatArray
    duration_s: float
    cast: Cast
    beam_times_s: FloatArray | None = None  # (S, N) true beam times (servo clock), for the warm-up drift
    scans_cast: NDArray[np.bool_] | None = None  # (S,) the scans cast_geometry's ``scans`` chose; None: all, unchosen


def cast_geometry(scenario: Scenario, *, scene: Scene | None = None, noise: bool = True,
                  progress: Callable[[int, int], None] | None = None, threads: int | Forked | None = None,
                  footprint: str | None = None, scans: Callable[[FloatArray], NDArray[np.bool_]] | None = None
                  ) -> Geometry:
    """Cast the scenario's rays once (no noise drawn): the laser phase comes from ``scenario.seed`` as in
    :func:`simulate`; ``noise=False`` casts for a noise-free sensor (range_max cut-off, see simulate); ``threads``:
    the cast's threads, or a forked helper process (lrfsim.cast.scans.cast_scans; the result does not depend on it);
    ``footprint``: "full", or "edges" for the footprint's ring cast only where it can change a beam
    (lrfsim.cast.chunks.cast_chunk_edges); default: the scenario's ``sensor.footprint_cast``;
    ``scans(beam_lambda_rad (S, N)) -> (S,) bool``: cast only those scans, the others read as no return (each
    scan is cast on its own, so the scans cast read as in the full cast, up to "edges"' choice of where to cast
    the ring, which compares a scan with the scans cast beside it)."""
    from .faults import scale_range_noise

    scenario = scale_range_noise(scenario)
    if not noise:
        scenario = _noise_free(scenario)
    if scene is None:
        from lrfsim.world.scene import build_scene

        scene = build_scene(scenario)
    sensor, servo = scenario.sensor, scenario.servo
    traj = servo_trajectory(servo)
    check_trajectory(traj)
    phase_s = laser_phase_s(scenario)
    starts_s = scan_start_times(traj.end_s, sensor, phase_s)
    times_s = beam_times(starts_s, sensor)
    beam_lambda = traj.angle(times_s)
    keep = None if scans is None else np.asarray(scans(beam_lambda), dtype=bool)
    if keep is None or keep.all():
        cast = cast_scans(scene, sensor, beam_lambda, progress=progress, threads=threads, footprint=footprint)
    else:
        cast = _in_scans(cast_scans(scene, sensor, beam_lambda[keep], progress=progress, threads=threads,
                                    footprint=footprint), keep)
    return Geometry(scenario_name=scenario.name, scene=scene, phase_s=phase_s, starts_s=starts_s,
                    beam_lambda_rad=beam_lambda, duration_s=traj.end_s, cast=cast, beam_times_s=times_s,
                    scans_cast=keep)


def laser_phase_s(scenario: Scenario) -> float:
    """When the laser's first scan starts [s] (servo clock, in [0, scan_period_s)): drawn from ``scenario.seed``
    (the laser runs free), or, with ``servo.mode: step``, timed to the steps (lrfsim.sensors.servo.step_scan_phase_s:
    every scan centred in a step's standstill)."""
    if scenario.servo.mode == "step":
        return step_scan_phase_s(scenario.servo, scenario.sensor)
    rng = np.random.default_rng([scenario.seed, _RNG_PHASE])
    return float(rng.uniform(0.0, scenario.sensor.scan_period_s))


def _in_scans(cast: Cast, keep: NDArray[np.bool_]) -> Cast:
    """A cast of the scans ``keep`` (S,) placed among all S scans, the others without a return."""
    def place(a: FloatArray, fill: float) -> FloatArray:
        out = np.full((keep.size, *a.shape[1:]), fill)
        out[keep] = a
        return out

    echoes = cast.echo_ranges_m is not None and cast.echo_power is not None
    return replace(cast, ranges_m=place(cast.ranges_m, np.nan), intensities=place(cast.intensities, 0.0),
                   echo_ranges_m=place(cast.echo_ranges_m, np.nan) if echoes else None,  # type: ignore[arg-type]
                   echo_power=place(cast.echo_power, 0.0) if echoes else None)  # type: ignore[arg-type]


def joined(a: Geometry, b: Geometry) -> Geometry:
    """Two casts of one scenario's geometry over disjoint sets of scans (``cast_geometry(..., scans=...)``), as
    one: each scan's returns from the cast that cast it."""
    ca, cb = a.cast, b.cast

    def join(x: FloatArray | None, y: FloatArray | None) -> FloatArray | None:
        return None if x is None or y is None else np.where(np.isnan(x), y, x)

    cast = replace(ca, ranges_m=np.where(np.isnan(ca.ranges_m), cb.ranges_m, ca.ranges_m),
                   intensities=ca.intensities + cb.intensities, echo_ranges_m=join(ca.echo_ranges_m, cb.echo_ranges_m),
                   echo_power=None if ca.echo_power is None or cb.echo_power is None else ca.echo_power + cb.echo_power,
                   n_rays=ca.n_rays + cb.n_rays, n_calls=ca.n_calls + cb.n_calls,
                   cast_time_s=ca.cast_time_s + cb.cast_time_s, total_time_s=ca.total_time_s + cb.total_time_s,
                   max_origin_error_m=max(ca.max_origin_error_m, cb.max_origin_error_m),
                   max_parallax_correction_m=max(ca.max_parallax_correction_m, cb.max_parallax_correction_m))
    both = None if a.scans_cast is None or b.scans_cast is None else a.scans_cast | b.scans_cast
    return replace(a, cast=cast, scans_cast=None if both is None or both.all() else both)


def _noise_free(scenario: Scenario) -> Scenario:
    return scenario.model_copy(update={"sensor": scenario.sensor.model_copy(
        update={"noise": False, "quantisation_m": 0.0})})


def simulate_from_geometry(scenario: Scenario, geometry: Geometry, *, noise: bool = True) -> SimResult:
    """A recording of ``scenario`` on a geometry cast before: only the noise is drawn (sensor noise, tape, faults,
    from ``scenario.seed``). The laser phase is the geometry's (for a geometry cast with another seed it is not
    the one ``scenario.seed`` would draw): the scenario must otherwise be the one the geometry was cast from."""
    from .faults import apply_faults, scale_range_noise

    t0 = time.perf_counter()
    scenario = scale_range_noise(scenario)
    if not noise:
        scenario = _noise_free(scenario)
    scene = geometry.scene
    sensor, servo = scenario.sensor, scenario.servo
    lid = sensor_model(geometry.cast, sensor, np.random.default_rng([scenario.seed, _RNG_SENSOR]),
                       geometry.beam_times_s)
    joints = joint_samples(servo_trajectory(servo), servo, geometry.starts_s)
    tape = measure_tape(scene.marker_ids, scene.markers_W, scenario.tape,
                        np.random.default_rng([scenario.seed, _RNG_TAPE]))
    truth = SimTruth(dh=scenario.rig.dh.to_dh(), mount=scenario.rig.mount.to_pose(),
                     marker_ids=tuple(scene.marker_ids), markers_W=np.array(scene.markers_W, dtype=float),
                     marker_radius_m=scene.marker_radius_m, clock_offset_s=servo.clock_offset_s,
                     tunnel=dict(scene.tunnel_truth) if scene.tunnel_truth is not None else None,
                     systematic=systematic_truth(sensor))
    stats = SimStats(n_rays=lid.n_rays, n_calls=lid.n_calls, cast_time_s=lid.cast_time_s,
                     lidar_time_s=lid.total_time_s, total_time_s=time.perf_counter() - t0 + geometry.cast.total_time_s,
                     max_origin_error_m=lid.max_origin_error_m, max_direction_error_rad=lid.max_direction_error_rad,
                     max_parallax_correction_m=lid.max_parallax_correction_m)
    result = SimResult(name=scenario.name, scan_stamps_s=laser_time(geometry.starts_s, servo.clock_offset_s),
                       mu_rad=beam_angles(sensor), ranges_m=lid.ranges_m, intensities=lid.intensities,
                       beam_lambda_rad=geometry.beam_lambda_rad, joints=joints, tape=tape, truth=truth, stats=stats,
                       duration_s=geometry.duration_s, echo_ranges_m=lid.echo_ranges_m,
                       echo_intensities=lid.echo_intensities)
    return apply_faults(result, scenario)


def simulate(scenario: Scenario, progress: Callable[[int, int], None] | None = None, *,
             scene: Scene | None = None, noise: bool = True, threads: int | None = None,
             footprint: str | None = None) -> SimResult:
    """Simulate a scenario's recording. ``progress(done_scans, total_scans)`` is called while scanning.

    ``scene`` defaults to ``lrfsim.world.scene.build_scene(scenario)`` (pass one to reuse or replace it).
    The scenario's ``faults`` are injected (lrfsim.simulation.faults): the range noise scale before, the others after
    simulating. ``noise=False`` casts the rays without the range and intensity noise and without the range
    quantisation, whatever ``sensor.noise`` says (the mixed-pixel footprint stays): the noise-free geometry that
    ``lrfsim plan`` predicts from. The same as ``simulate_from_geometry(scenario, cast_geometry(scenario))``.
    ``threads``: the cast's threads (default: the cores available, lrfsim.cast.scans.default_threads); ``footprint``:
    see :func:`cast_geometry`.
    """
    geometry = cast_geometry(scenario, scene=scene, noise=noise, progress=progress, threads=threads,
                             footprint=footprint)
    return simulate_from_geometry(scenario, geometry, noise=noise)


__all__ = ["Geometry", "SimResult", "SimStats", "SimTruth", "cast_geometry", "joined", "laser_phase_s",
           "simulate", "simulate_from_geometry", "systematic_truth"]
