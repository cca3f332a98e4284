"""Fault injection: what goes wrong on a real rig, applied to a simulated recording before it is written.

Every fault is a pure function ``SimResult -> SimResult`` (a new result; arrays are copied, never modified in
place) and adds what it did to ``SimResult.faults`` (written to ground_truth.yaml under ``faults``), so a test
knows exactly what was injected. Each has a fixed number k (below; a new fault takes the next free number,
wherever it is applied), and those that draw random numbers draw from their own stream,
``default_rng([seed, 0x6661756C, k])``, so switching one fault on does not reshuffle the others (nor the sensor
noise, tape or laser phase of lrfsim.simulation.simulate).

The scenario's ``faults:`` section (lrfsim.scenario.sections.FaultsConfig), applied in the order listed:

0. ``range_noise_scale: k``: every ``sensor.noise_bands`` sigma times k, before simulating
   (:func:`scale_range_noise`); recorded as ``range_noise_scale``.
1. ``tape_outliers: [{pair: [id_i, id_j] | row, error_m}]``: error_m added to that measured pair
   (distances.csv); recorded per pair with the true and the written distance.
2. ``inverted_servo: true``: JointState positions and velocities negated (a servo mounted the other way
   round); the truth (``beam_lambda_rad``, ``joints.true_positions_rad``) is unchanged.
8. ``gear_ratio: k``: JointState positions and velocities times k (a wrong gear ratio or encoder counts per
   revolution in the driver; after the inversion, before the encoder spikes, which are then in the published
   angle); the truth is unchanged. Recorded as ``gear_ratio`` (k).
3. ``occluded_markers: N``: N markers (among those with returns) covered: every bright return whose ray passes
   within the marker (radius + footprint + 2 mm) gets the range and intensity of the surface around it,
   interpolated in its scan from the nearest unaffected beams on both sides (NaN and 0 when there are none).
   Recorded: the marker ids and the (scan, beam) cells changed.
4. ``false_blobs: N``: N bright spots of 1-3 scans x 2-4 beams on non-marker surfaces (every cell's
   reprojected truth point >= 0.2 m from every marker centre, spots >= 20 beams or 10 scans apart): the
   intensity of a retroreflector at that range, gain * rho_retro * (r_ref / r)^2 * (1 + noise), saturated.
   Recorded: each spot's cells.
5. ``dropped_scans_fraction: f``: round(f S) random scans removed (all arrays with a scan axis). Recorded:
   the original indices of the removed scans.
9. ``joint_rate_hz: f``: the joint states thinned to at most f: every n-th sample kept from the first, n =
   ceil(servo.rate_hz / f) (a servo polled slowly; before the encoder spikes, so their indices are those of
   the written stream). Recorded: f (requested_hz), n (keep_every) and the rate written, servo.rate_hz / n.
6. ``encoder_spikes: N``: N random joint-state samples get +-encoder_spike_rad (random sign) on their
   position. Recorded: sample index and the jump.
7. ``stamp_latency_s: L``, ``stamp_jitter_s: J``: scan stamps taken at receive time, each stamp moved later by
   L + uniform [0, J) (:func:`receive_stamps`). Recorded: L, J and the largest delay.
10. ``angle_increment_off_by_one: true``: the LaserScans declare angle_increment = (angle_max - angle_min) / N
    instead of / (N - 1) (N beams; a driver's off-by-one), angle_min and angle_max unchanged: a reader that
    places beam i at angle_min + i angle_increment puts the last beam (N - 1) / N of the span from the first.
    The ranges stay where the beams truly were (only ``SimResult.declared_angle_increment_rad``, which the bag
    writer declares, changes). Recorded: the true and the declared increment.
11. ``range_scale: k``: every reported range (and every echo's) times k (a scanner whose range scale is off: its
    time-of-flight clock, or a driver's unit); after the others. The truth is unchanged. Recorded as
    ``range_scale`` (k).
12. ``joint_gap_s: L`` (``joint_gap_at_s: t``): the joint states of L seconds centred on the servo-clock time t
    removed (a joint-state stream that stalled; by default t is the middle of the servo's first turnaround, the
    middle of the joint states for a spin); after the thinning, before the encoder spikes (:func:`joint_gap`).
    Recorded: the gap's start, end and length on the servo clock and the number of samples removed.
13. ``joint_clock_step_s: X`` (``joint_clock_step_at_s: t``): the servo computer's clock steps by X (negative:
    back, an NTP correction) at its true time t (default: the middle of the joint states): every JointState stamp
    from then on is X later, its receive time in the bag is not (the recorder's clock does not step); last of all
    (:func:`clock_step`). Recorded as ``joint_clock_step``: X, t, the index of the first stamp moved, how many, and
    the true laser-minus-servo offset after the step (``clock_offset_after_s``, servo.clock_offset_s - X).
14. ``scan_clock_step_s: X`` (``scan_clock_step_at_s: t``): the same for the laser's clock and the LaserScan
    stamps (default t: the middle of the scans). Recorded as ``scan_clock_step``, the offset after it
    servo.clock_offset_s + X.

Not a fault of this module: ``servo.clock_offset_s`` (laser stamp - servo stamp) already simulates an unknown
laser-servo clock offset (the recording does not declare it; ground_truth.yaml has it as clock_offset_s).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfcal.model.kinematics import Params, beam_rays_M, points_W, transform_points
from lrfsim.scenario.file import Scenario
from lrfsim.scenario.sections import FaultsConfig, NoiseBand, TapeOutlier
from lrfsim.sensors.tape import TapeResult

if TYPE_CHECKING:  # annotations only: simulate.py applies these faults (no import circle)
    from .result import SimResult

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

_RNG_FAULTS = 0x6661756C
#: a return is "bright" (a marker's) above this many times the brightest Lambertian surface at its range
BRIGHT_FACTOR = 3.0
#: false blobs keep at least this distance from every marker centre
FALSE_BLOB_CLEARANCE_M = 0.2


def _rng(scenario: Scenario, k: int) -> np.random.Generator:
    return np.random.default_rng([scenario.seed, _RNG_FAULTS, k])


def _with_record(result: SimResult, key: str, value: Any, **changes: Any) -> SimResult:
    return replace(result, faults={**result.faults, key: value}, **changes)


def scale_range_noise(scenario: Scenario) -> Scenario:
    """The scenario with every range noise band's sigma (and the range-proportional noise) times
    ``faults.range_noise_scale`` (unchanged at 1)."""
    k = scenario.faults.range_noise_scale
    if k == 1.0:
        return scenario
    bands = tuple(NoiseBand(up_to_m=b.up_to_m, sigma_m=b.sigma_m * k) for b in scenario.sensor.noise_bands)
    fraction = scenario.sensor.noise_range_fraction * k
    return scenario.model_copy(update={"sensor": scenario.sensor.model_copy(
        update={"noise_bands": bands, "noise_range_fraction": fraction})})


def tape_outliers(result: SimResult, outliers: tuple[TapeOutlier, ...]) -> SimResult:
    """Add each outlier's error_m to its measured pair (by ids, either order, or by row)."""
    if not outliers:
        return result
    tape = result.tape
    ids = tape.marker_ids
    d = tape.distances_m.copy()
    record = []
    for o in outliers:
        if isinstance(o.pair, int):
            if o.pair >= len(d):
                raise InputError(f"faults.tape_outliers: pair row {o.pair} is beyond the {len(d)} measured pairs")
            row = o.pair
        else:
            try:
                i, j = ids.index(o.pair[0]), ids.index(o.pair[1])
            except ValueError:
                raise InputError(f"faults.tape_outliers: unknown marker id in {list(o.pair)} "
                                 f"(ids: {ids[0]}..{ids[-1]})") from None
            rows = np.nonzero(((tape.pairs[:, 0] == i) & (tape.pairs[:, 1] == j))
                              | ((tape.pairs[:, 0] == j) & (tape.pairs[:, 1] == i)))[0]
            if rows.size == 0:
                raise InputError(f"faults.tape_outliers: pair {list(o.pair)} is not among the measured pairs")
            row = int(rows[0])
        i, j = (int(v) for v in tape.pairs[row])
        before = float(d[row])
        d[row] += o.error_m
        if d[row] <= 0:
            raise InputError(f"faults.tape_outliers: pair {ids[i]}-{ids[j]} would measure {d[row]:.3f} m (<= 0)")
        record.append({"pair": [ids[i], ids[j]], "row": row, "error_m": float(o.error_m),
                       "measured_before_m": before, "measured_m": float(d[row])})
    new_tape = TapeResult(marker_ids=ids, pairs=tape.pairs.copy(), distances_m=d)
    return _with_record(result, "tape_outliers", record, tape=new_tape)


def invert_servo(result: SimResult) -> SimResult:
    """JointState positions and velocities negated; the truth is unchanged."""
    j = result.joints
    joints = replace(j, positions_rad=-j.positions_rad, velocities_rad_s=-j.velocities_rad_s)
    return _with_record(result, "inverted_servo", True, joints=joints)


def _truth_params(result: SimResult) -> Params:
    return Params(result.truth.mount, result.truth.dh)


def bright_mask(result: SimResult, scenario: Scenario) -> NDArray[np.bool_]:
    """(S, N) returns brighter than BRIGHT_FACTOR x the brightest Lambertian surface at their range (noise
    included): the retroreflector returns."""
    it = scenario.sensor.intensity
    sc = scenario.scene
    rho = max([sc.materials.painted_steel, sc.materials.board] + [m.reflectivity for m in sc.meshes]
              + [b.reflectivity for b in sc.boxes] + ([sc.room.reflectivity] if sc.room is not None else []))
    r = result.ranges_m
    with np.errstate(invalid="ignore", divide="ignore"):
        surface = it.gain_counts * rho * (it.ref_range_m / r) ** 2 * (1 + 4 * it.relative_noise)
        return np.isfinite(r) & (result.intensities > BRIGHT_FACTOR * np.minimum(surface, it.saturation_counts))


def marker_returns(result: SimResult, scenario: Scenario, among: NDArray[np.bool_] | None = None) -> IntArray:
    """(S, N) index of the marker each bright return belongs to (-1: none): its ray (truth geometry) passes
    within radius + footprint + 2 mm of the marker centre, ahead of the scanner. ``among`` (S, N): the returns to
    consider instead of the bright ones (:func:`bright_mask`), e.g. the calibration's detections
    (:func:`detected_mask`)."""
    from lrfcal.model.marker import footprint_radius_m, ray_to_centre  # (scipy.special: not for the simulation)

    S, N = result.ranges_m.shape
    out = np.full((S, N), -1, dtype=np.int64)
    radius_m = result.truth.marker_radius_m
    if radius_m is None or len(result.truth.markers_W) == 0:
        return out
    s_idx, b_idx = np.nonzero(bright_mask(result, scenario) if among is None else among)
    if s_idx.size == 0:
        return out
    lam = result.beam_lambda_rad[s_idx, b_idx]
    mu = result.mu_rad[b_idx]
    o_M, d_M = beam_rays_M(lam, mu, result.truth.dh)
    T = result.truth.mount.matrix()
    o_W = transform_points(T, o_M)
    d_W = d_M @ T[:3, :3].T
    _, t, e = ray_to_centre(o_W[:, None, :], d_W[:, None, :], result.truth.markers_W[None, :, :])  # (K, n)
    perp = np.linalg.norm(e, axis=-1)
    reach = radius_m + footprint_radius_m(t, scenario.sensor.divergence_rad) + 0.002
    perp = np.where((t > 0) & (perp < reach), perp, np.inf)
    k = perp.argmin(1)
    ok = np.isfinite(perp[np.arange(len(k)), k])
    out[s_idx[ok], b_idx[ok]] = k[ok]
    return out


def detected_mask(result: SimResult, scenario: Scenario) -> NDArray[np.bool_]:
    """(S, N) the returns the calibration's detection (lrfcal.stages.detection.detect) puts in a blob: what a
    calibration
    of this recording sees as marker returns. Near the scanner a marker and the surface behind it both saturate,
    and a brightness bound (:func:`bright_mask`) keeps only a marker's edge beams there, where the detection's
    contrast keeps none."""
    from lrfcal import Scans, detect

    s = scenario.sensor
    det = detect(Scans(result.scan_stamps_s, result.ranges_m, result.intensities, result.mu_rad,
                       s.time_increment_s, s.scan_period_s, s.range_min_m, s.range_max_m))
    mask = np.zeros(result.ranges_m.shape, dtype=bool)
    for b in det.blobs:
        mask[b.scan_idx, b.beam_idx] = True
    return mask


def occlude_markers(result: SimResult, scenario: Scenario, n: int) -> SimResult:
    """Cover n random markers (among those with returns); see the module docstring."""
    if n == 0:
        return result
    rng = _rng(scenario, 3)
    owner = marker_returns(result, scenario)
    seen = np.unique(owner[owner >= 0])
    chosen = np.sort(rng.choice(seen, size=min(n, seen.size), replace=False)) if seen.size else seen
    hit = np.isin(owner, chosen)
    ranges, intens = result.ranges_m.copy(), result.intensities.copy()
    valid = np.isfinite(ranges) & ~hit
    cells = np.argwhere(hit)
    for s in np.unique(cells[:, 0]):
        beams = cells[cells[:, 0] == s, 1]
        good = np.nonzero(valid[s])[0]
        for b in beams:
            left, right = good[good < b], good[good > b]
            nb = ([left[-1]] if left.size else []) + ([right[0]] if right.size else [])
            if not nb:
                ranges[s, b], intens[s, b] = np.nan, 0.0
            elif len(nb) == 1:
                ranges[s, b], intens[s, b] = ranges[s, nb[0]], intens[s, nb[0]]
            else:
                w = (b - nb[0]) / (nb[1] - nb[0])
                ranges[s, b] = (1 - w) * ranges[s, nb[0]] + w * ranges[s, nb[1]]
                intens[s, b] = np.round((1 - w) * intens[s, nb[0]] + w * intens[s, nb[1]])
    ids = result.truth.marker_ids
    record = {"markers": [ids[int(k)] for k in chosen], "cells": cells.tolist(), "n_cells": int(len(cells))}
    return _with_record(result, "occluded_markers", record, ranges_m=ranges, intensities=intens)


def add_false_blobs(result: SimResult, scenario: Scenario, n: int) -> SimResult:
    """n bright spots on non-marker surfaces; see the module docstring."""
    if n == 0:
        return result
    rng = _rng(scenario, 4)
    it = scenario.sensor.intensity
    rho = scenario.scene.materials.retroreflector
    S, N = result.ranges_m.shape
    params = _truth_params(result)
    C = result.truth.markers_W
    ranges, intens = result.ranges_m, result.intensities.copy()
    bright = bright_mask(result, scenario)
    spots: list[dict[str, Any]] = []
    centres: list[tuple[int, int]] = []
    for _ in range(200 * n):
        if len(spots) == n:
            break
        ns, nb = int(rng.integers(1, 4)), int(rng.integers(2, 5))
        s0, b0 = int(rng.integers(0, max(S - ns + 1, 1))), int(rng.integers(0, max(N - nb + 1, 1)))
        if any(abs(s0 - s) < 10 and abs(b0 - b) < 20 for s, b in centres):
            continue
        ss, bb = np.meshgrid(np.arange(s0, min(s0 + ns, S)), np.arange(b0, min(b0 + nb, N)), indexing="ij")
        ss, bb = ss.ravel(), bb.ravel()
        r = ranges[ss, bb]
        if not np.all(np.isfinite(r)) or bright[ss, bb].any():
            continue
        p = points_W(r, result.beam_lambda_rad[ss, bb], result.mu_rad[bb], params)
        if len(C) and np.linalg.norm(p[:, None, :] - C[None], axis=-1).min() < FALSE_BLOB_CLEARANCE_M:
            continue
        level = it.gain_counts * rho * (it.ref_range_m / r) ** 2
        level = level * np.maximum(0.0, 1 + it.relative_noise * rng.standard_normal(r.size))
        intens[ss, bb] = np.round(np.minimum(level, it.saturation_counts))
        centres.append((s0, b0))
        spots.append({"cells": np.column_stack([ss, bb]).tolist()})
    return _with_record(result, "false_blobs", spots, intensities=intens)


def drop_scans(result: SimResult, scenario: Scenario, fraction: float) -> SimResult:
    """round(fraction S) random scans removed."""
    S = result.ranges_m.shape[0]
    k = int(round(fraction * S))
    if k == 0:
        return result
    drop = np.sort(_rng(scenario, 5).choice(S, size=k, replace=False))
    keep = np.ones(S, dtype=bool)
    keep[drop] = False
    echoes = {} if result.echo_ranges_m is None or result.echo_intensities is None else {
        "echo_ranges_m": result.echo_ranges_m[keep], "echo_intensities": result.echo_intensities[keep]}
    return _with_record(result, "dropped_scans", drop.tolist(), scan_stamps_s=result.scan_stamps_s[keep],
                        ranges_m=result.ranges_m[keep], intensities=result.intensities[keep],
                        beam_lambda_rad=result.beam_lambda_rad[keep], **echoes)


def encoder_spikes(result: SimResult, scenario: Scenario, n: int, spike_rad: float) -> SimResult:
    """n random joint samples get +-spike_rad on their reported position."""
    if n == 0:
        return result
    rng = _rng(scenario, 6)
    J = result.joints.positions_rad.size
    idx = np.sort(rng.choice(J, size=min(n, J), replace=False))
    delta = spike_rad * rng.choice([-1.0, 1.0], size=idx.size)
    pos = result.joints.positions_rad.copy()
    pos[idx] += delta
    record = [{"index": int(i), "delta_rad": float(d)} for i, d in zip(idx, delta, strict=True)]
    return _with_record(result, "encoder_spikes", record, joints=replace(result.joints, positions_rad=pos))


def receive_stamps(result: SimResult, scenario: Scenario, latency_s: float, jitter_s: float) -> SimResult:
    """Scan stamps taken when the scan arrives, not when its first beam fires (as urg_node stamps before its
    latency correction): every stamp + latency_s + uniform [0, jitter_s). The beams' true times are unchanged;
    only the stamps the recording carries move."""
    if latency_s == 0.0 and jitter_s == 0.0:
        return result
    rng = _rng(scenario, 7)
    delay = latency_s + jitter_s * rng.random(result.scan_stamps_s.size)
    record = {"latency_s": float(latency_s), "jitter_s": float(jitter_s), "max_delay_s": float(delay.max())}
    return _with_record(result, "receive_stamps", record, scan_stamps_s=result.scan_stamps_s + delay)


def scale_joints(result: SimResult, ratio: float) -> SimResult:
    """JointState positions and velocities times ``ratio`` (a wrong gear ratio); the truth is unchanged."""
    if ratio == 1.0:
        return result
    j = result.joints
    joints = replace(j, positions_rad=j.positions_rad * ratio, velocities_rad_s=j.velocities_rad_s * ratio)
    return _with_record(result, "gear_ratio", float(ratio), joints=joints)


def thin_joints(result: SimResult, scenario: Scenario, rate_hz: float | None) -> SimResult:
    """Every n-th joint state kept (from the first), n = ceil(servo.rate_hz / rate_hz): at most ``rate_hz``."""
    if rate_hz is None:
        return result
    n = max(1, math.ceil(scenario.servo.rate_hz / rate_hz * (1.0 - 1e-12)))
    j = result.joints
    joints = replace(j, stamps_s=j.stamps_s[::n], positions_rad=j.positions_rad[::n],
                     velocities_rad_s=j.velocities_rad_s[::n], true_positions_rad=j.true_positions_rad[::n])
    record = {"requested_hz": float(rate_hz), "keep_every": int(n), "rate_hz": float(scenario.servo.rate_hz / n)}
    return _with_record(result, "joint_rate_hz", record, joints=joints)


def first_turnaround_s(result: SimResult) -> float:
    """Servo-clock time of the middle of the motor's first reversal (the standstill between the first two passes,
    from the true joint positions); the middle of the joint states when the motor never reverses (a spin)."""
    j = result.joints
    t, q = j.stamps_s, j.true_positions_rad
    step = np.diff(q)
    moving = np.flatnonzero(np.abs(step) > 1e-9)
    if moving.size:
        first = np.sign(step[moving[0]])
        back = moving[np.sign(step[moving]) != first]
        if back.size:
            last_fwd = moving[moving < back[0]][-1]
            return float(0.5 * (t[last_fwd + 1] + t[back[0]]))
    return float(0.5 * (t[0] + t[-1]))


def joint_gap(result: SimResult, length_s: float | None, at_s: float | None) -> SimResult:
    """The joint states of ``length_s`` centred on the servo-clock time ``at_s`` (default: the first turnaround,
    :func:`first_turnaround_s`) removed; at least two samples must remain."""
    if length_s is None:
        return result
    j = result.joints
    centre = first_turnaround_s(result) if at_s is None else float(at_s)
    t0, t1 = centre - 0.5 * length_s, centre + 0.5 * length_s
    keep = (j.stamps_s < t0) | (j.stamps_s > t1)
    if keep.sum() < 2:
        raise InputError(f"faults.joint_gap_s: a gap of {length_s:g} s at {centre:g} s leaves {int(keep.sum())} of the "
                         f"{keep.size} joint states ({j.stamps_s[0]:g}-{j.stamps_s[-1]:g} s); make it shorter")
    joints = replace(j, stamps_s=j.stamps_s[keep], positions_rad=j.positions_rad[keep],
                     velocities_rad_s=j.velocities_rad_s[keep], true_positions_rad=j.true_positions_rad[keep])
    record = {"start_s": float(t0), "end_s": float(t1), "length_s": float(length_s),
              "n_removed": int((~keep).sum())}
    return _with_record(result, "joint_gap", record, joints=joints)


def off_by_one_increment(result: SimResult, scenario: Scenario) -> SimResult:
    """The LaserScans declare (angle_max - angle_min) / N as angle_increment instead of / (N - 1)."""
    sensor = scenario.sensor
    n = sensor.n_beams
    declared = (n - 1) * sensor.angle_increment_rad / n
    record = {"true_angle_increment_rad": float(sensor.angle_increment_rad), "declared_angle_increment_rad":
              float(declared)}
    return _with_record(result, "angle_increment_off_by_one", record, declared_angle_increment_rad=declared)


def scale_ranges(result: SimResult, scale: float) -> SimResult:
    """Every reported range, and every echo's, times ``scale`` (a range scale error); the truth is unchanged."""
    if scale == 1.0:
        return result
    echoes = None if result.echo_ranges_m is None else result.echo_ranges_m * scale
    return _with_record(result, "range_scale", float(scale), ranges_m=result.ranges_m * scale, echo_ranges_m=echoes)


def clock_step(result: SimResult, scenario: Scenario, clock: str, step_s: float | None, at_s: float | None
               ) -> SimResult:
    """The stamps of one clock (``clock`` "joint": the JointStates', "scan": the LaserScans') from its true time
    ``at_s`` on (default: the middle of the stream) moved by ``step_s``; the bag's log times stay the true ones
    (:func:`true_stamps`)."""
    if step_s is None:
        return result
    stamps = result.joints.stamps_s if clock == "joint" else result.scan_stamps_s
    at = float(0.5 * (stamps[0] + stamps[-1])) if at_s is None else float(at_s)
    first = int(np.searchsorted(stamps, at))
    moved = stamps.copy()
    moved[first:] += step_s
    sign = -1.0 if clock == "joint" else 1.0  # laser stamp - servo stamp after the step
    record = {"step_s": float(step_s), "at_s": at, "first_index": first, "n_moved": int(stamps.size - first),
              "clock_offset_after_s": float(scenario.servo.clock_offset_s + sign * step_s)}
    if clock == "joint":
        return _with_record(result, "joint_clock_step", record, joints=replace(result.joints, stamps_s=moved))
    return _with_record(result, "scan_clock_step", record, scan_stamps_s=moved)


def true_stamps(result: SimResult, clock: str) -> FloatArray:
    """The stamps of ``clock`` ("joint" or "scan") with an injected clock step (:func:`clock_step`) undone: the times
    the recorder logs the messages at (lrfsim.simulation.recording)."""
    stamps = result.joints.stamps_s if clock == "joint" else result.scan_stamps_s
    step = result.faults.get(f"{clock}_clock_step")
    if step is None:
        return stamps
    out = stamps.copy()
    out[int(step["first_index"]):] -= float(step["step_s"])
    return out


def apply_faults(result: SimResult, scenario: Scenario) -> SimResult:
    """Every fault of ``scenario.faults`` except the range noise scale (applied before simulating), in the
    module docstring's order; the result's ``faults`` record lists what was done."""
    f: FaultsConfig = scenario.faults
    if f.range_noise_scale != 1.0:
        result = _with_record(result, "range_noise_scale", float(f.range_noise_scale))
    result = tape_outliers(result, f.tape_outliers)
    if f.inverted_servo:
        result = invert_servo(result)
    result = scale_joints(result, f.gear_ratio)
    result = occlude_markers(result, scenario, f.occluded_markers)
    result = add_false_blobs(result, scenario, f.false_blobs)
    result = drop_scans(result, scenario, f.dropped_scans_fraction)
    result = thin_joints(result, scenario, f.joint_rate_hz)
    result = joint_gap(result, f.joint_gap_s, f.joint_gap_at_s)
    result = encoder_spikes(result, scenario, f.encoder_spikes, f.encoder_spike_rad)
    result = receive_stamps(result, scenario, f.stamp_latency_s, f.stamp_jitter_s)
    if f.angle_increment_off_by_one:
        result = off_by_one_increment(result, scenario)
    result = scale_ranges(result, f.range_scale)
    result = clock_step(result, scenario, "joint", f.joint_clock_step_s, f.joint_clock_step_at_s)
    return clock_step(result, scenario, "scan", f.scan_clock_step_s, f.scan_clock_step_at_s)


__all__ = ["BRIGHT_FACTOR", "FALSE_BLOB_CLEARANCE_M", "add_false_blobs", "apply_faults", "bright_mask", "clock_step",
           "detected_mask",
           "drop_scans", "encoder_spikes", "first_turnaround_s", "invert_servo", "joint_gap", "marker_returns",
           "occlude_markers", "off_by_one_increment", "receive_stamps", "scale_joints", "scale_range_noise",
           "scale_ranges", "tape_outliers", "thin_joints", "true_stamps"]
