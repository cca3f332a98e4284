"""Stage 6b: the marker returns solved jointly with the ordinary returns from the surfaces the markers sit on
(lrfcal.stages.surfaces), and with every other plane of the scene when asked; the intrinsic scales the data contradict
found by their score tests (:func:`most_off`).

The surface returns are chosen at an estimate (lrfcal.stages.surfaces.surface_returns: the gate on a return's distance
from its plane) and chosen again at the joint estimate while it moves them (lrfcal.stages.surfaces.RESELECT_M): the
marker-only estimate the first choice is made at can be centimetres off where the markers alone do not determine
the DH parameters (a fast one-pass sweep: one scan line per marker).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Protocol

from lrfcal.estimate import observability
from lrfcal.estimate.problem import OnPlanes
from lrfcal.estimate.solve import Solver
from lrfcal.model.motor import Clock, MotorClock
from lrfcal.stages import surfaces, timing
from lrfcal.stages.targetless import SceneConfig, merge_returns, scene_plane_returns
from lrfcal.types import Detections, JointStates, MarkerMap, Noted, Observations, Recording, Solution

#: an intrinsic scale whose score test steps this many sigma from 1 is estimated (a gear ratio, an angle increment)
SCALE_Z_LIMIT = 4.0
#: what is off when a scale held at 1 by default is not 1 (lrfcal.model.unknowns, kind "intrinsic"). The bearing
#: scale (beam_scale) is not tested: on tunnel_v_systematic the unmodelled range errors move its score test 15 sigma
#: from 1 (0.99147 +- 0.00057, truth 1), and estimating it puts the mount 10 mm off
SCALES = {"motor_scale": "the servo's motor-angle scale (a gear ratio or counts per turn in the joint states?)",
          "range_scale": "the scanner's range scale (ranges off in proportion to their length, or a range bias "
                         "growing with range read as one?)"}


def most_off(sol: Solution, max_chi2: float) -> Noted[str] | None:
    """The scale of :data:`SCALES` held at 1 that the data contradict most (its score test on ``sol``,
    lrfcal.estimate.solve,
    beyond SCALE_Z_LIMIT sigma), with a note naming the value it steps to; None when none is. One at a time, the
    others tested again once it is free: a gear ratio 2 % off also stepped the range scale beyond 4 sigma, which
    it absorbs. None where ``sol``'s reduced chi-square is above ``max_chi2``: a score test means nothing where the
    model does not fit (three times the stated range noise stepped the range scale 4.4 sigma), and the chi-square
    check names that."""
    if not sol.reduced_chi2 <= max_chi2:
        return None
    z = {n: abs(v - 1.0) / s for n, (v, s) in sol.held_score.items() if n in SCALES and math.isfinite(s) and s > 0}
    name = max(z, key=z.__getitem__, default=None)
    if name is None or z[name] <= SCALE_Z_LIMIT:
        return None
    value, sigma = sol.held_score[name]
    return Noted(name, (f"{SCALES[name]} is off: about {value:.5f} +- {sigma:.5f} ({z[name]:.0f} sigma from 1): "
                        "estimated in every solve",))


class JointConfig(SceneConfig, Protocol):
    """The configuration the joint solve reads: its slice of lrfcal.config.CalibConfig (which satisfies it): the
    surfaces' options and, for every other plane of the scene, the scene's (lrfcal.stages.targetless.SceneConfig)."""

    @property
    def surfaces(self) -> bool: ...
    @property
    def surface_max_returns(self) -> int: ...
    @property
    def estimate_range_bias(self) -> bool: ...
    @property
    def all_planes(self) -> bool: ...


#: the joint result (:func:`with_surfaces`): the solution, the surfaces, their returns
JointFit = tuple[Solution, list[surfaces.Surface], surfaces.SurfaceReturns | None]


@dataclass(frozen=True)
class Recorded:
    """A recording as the joint solve reads it: the recording (its scans and nominal values), its joint states
    (with the servo's direction applied) and the marker returns detected in it."""

    recording: Recording
    joints: JointStates
    detections: Detections


def with_surfaces(marker_fit: Solution, matched: Observations, markers: MarkerMap, motor: MotorClock | None,
                  recorded: Recorded, config: JointConfig, fit: Solver) -> Noted[JointFit]:
    """6b from the marker-only solution ``marker_fit`` of the ``matched`` returns (``motor``: the clock model when
    the clock offset is estimated; ``fit``: lrfcal.estimate.solve.solve bound to the rig): every beam on the markers'
    planes
    solved jointly with the markers (and every other plane of the scene with ``config.all_planes``); the marker-only
    solution itself when ``config.surfaces`` is off or no surface return is found; with its notes."""
    ours = marker_fit
    if not config.surfaces:
        return Noted((ours, [], None))
    notes: list[str] = []
    scans, nominal = recorded.recording.scans, recorded.recording.nominal
    joints, detections = recorded.joints, recorded.detections
    n_beams = scans.ranges_m.shape[1]

    def times_at(i: surfaces.IntArray) -> surfaces.FloatArray:  # beam times of flat indices (K,), elementwise
        return scans.angle_times_at(i // n_beams, i % n_beams)

    selected_at, note = ours, None
    surface_list: list[surfaces.Surface] = []
    on_surfaces: surfaces.SurfaceReturns | None = None
    on_markers = surfaces.PlaneMarkers(markers.positions_W, nominal.marker_radius_m, max(markers.rms_m, 0.0005))
    selection = surfaces.SurfaceSelection(max_returns=config.surface_max_returns)
    for _ in range(surfaces.ROUNDS):  # the returns chosen again at the joint estimate while it moves them
        # the motor angles of the beams observe_surfaces reprojects only (elementwise: the same bits as the grid's)
        lambda_at = partial(_motor_angles_at, times_at, joints, selected_at.clock_offset_s)
        grid = surfaces.ReturnGrid(scans.ranges_m, scans.mu_rad, lambda_at, detections.labels, times_at)
        found = surfaces.observe_surfaces(grid, on_markers, selected_at.params, selection=selection,
                                          intrinsics=selected_at.intrinsic_values)
        if on_surfaces is None or len(found[1]):
            surface_list, on_surfaces = found
        if not len(found[1]):
            break
        joint = partial(fit, matched, markers, selected_at.params, surfaces=OnPlanes(on_surfaces, surface_list),
                        clock=Clock(motor, selected_at.clock_offset_s), held_scores=tuple(SCALES))
        ours = joint(estimate_range_bias=config.estimate_range_bias)
        if config.estimate_range_bias and not (max(ours.range_offset_sigma_m, ours.marker_range_bias_sigma_m)
                                               <= observability.RANGE_BIAS_LIMIT_M):
            note = (f"range offset and marker range bias not separable by this recording (1-sigma "
                    f"{ours.range_offset_sigma_m * 1000:.3g} / {ours.marker_range_bias_sigma_m * 1000:.3g} mm): "
                    "held at 0")
            ours = joint(estimate_range_bias=False)
        if surfaces.moved_m(on_surfaces, (selected_at.params, selected_at.intrinsic_values),
                            (ours.params, ours.intrinsic_values)) <= surfaces.RESELECT_M:
            break
        selected_at = ours  # after ROUNDS choices the last stands (fast sweeps settle in 3: 35, 2.4, 0.1 mm)
    if note:
        notes.append(note)
    if on_surfaces is not None and not len(on_surfaces) and config.estimate_range_bias:
        notes.append("range offset and marker range bias held at 0: without surface returns the markers alone "
                     "do not separate them from the marker radius and the mount")
    if config.all_planes:  # 6b generalised: every other plane of the scene too, as free planes
        others, other_planes = scene_plane_returns(scans, joints, ours, detections.labels >= 0,
                                                   list(surface_list), config)
        if len(others):
            on_surfaces = merge_returns(on_surfaces, others)
            surface_list = [*surface_list, *other_planes]
            ours = fit(matched, markers, ours.params, surfaces=OnPlanes(on_surfaces, surface_list),
                       clock=Clock(motor, ours.clock_offset_s),
                       estimate_range_bias=math.isfinite(ours.range_offset_sigma_m), held_scores=tuple(SCALES))
            notes.append(f"{len(other_planes)} more planes of the scene ({len(others)} returns) solved jointly as "
                         "free planes")
    return Noted((ours, list(surface_list), on_surfaces), tuple(notes))


def _motor_angles_at(times_at: Callable[[surfaces.IntArray], surfaces.FloatArray], joints: JointStates,
                     clock_offset_s: float, i: surfaces.IntArray) -> surfaces.FloatArray:
    """The motor angles (K,) of the beams of flat indices ``i`` (K,) at ``clock_offset_s`` (lrfcal.stages.timing)."""
    return timing.motor_angles(times_at(i), joints, clock_offset_s=clock_offset_s, tolerance_s=math.inf)


__all__ = ["SCALES", "JointConfig", "JointFit", "SCALE_Z_LIMIT", "Recorded", "most_off", "with_surfaces"]
