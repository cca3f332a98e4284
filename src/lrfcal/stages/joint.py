"""Stage 6b's choices: the surfaces the markers sit on and their ordinary returns (lrfcal.stages.surfaces), to solve
jointly with the marker returns, and every other plane of the scene when asked; the range bias held where the
recording does not separate it; the intrinsic scales the data contradict, found by their score tests
(:func:`most_off`). The rounds that solve with them are lrfcal.stages.refinement's.

The surface returns are chosen at an estimate (lrfcal.stages.surfaces.surface_returns: the gate on a return's distance
from its plane) and chosen again at the joint estimate while it moves them (lrfcal.stages.surfaces.RESELECT_M): the
marker-only estimate the first choice is made at can be centimetres off where the markers alone do not determine
the DH parameters (a fast one-pass sweep: one scan line per marker).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from typing import Protocol

from lrfcal.estimate import observability
from lrfcal.model.unknowns import BY_NAME
from lrfcal.stages import surfaces, timing
from lrfcal.stages.targetless import SceneConfig, merge_returns, scene_plane_returns
from lrfcal.types import Detections, JointStates, MarkerMap, Noted, Recording, Solution

#: an intrinsic held at its start by default whose score test steps this many sigma from it is estimated (a gear
#: ratio, a range scale, ranges that grow with the incidence)
SCALE_Z_LIMIT = 4.0
#: what is off when an intrinsic held at its start by default is not (lrfcal.model.unknowns, kind "intrinsic"): the
#: scales (held at 1) and the incidence bias (held at 0). The bearing scale (beam_scale) is not tested: on
#: tunnel_v_systematic the unmodelled range errors moved its score test 15 sigma from 1 (0.99147 +- 0.00057, truth 1),
#: and estimating it put the mount 10 mm off
SCALES = {"motor_scale": "the servo's motor-angle scale (a gear ratio or counts per turn in the joint states?)",
          "range_scale": "the scanner's range scale (ranges off in proportion to their length, or a range bias "
                         "growing with range read as one?)",
          "incidence_bias": "the ranges' growth with the beam's incidence on the surface (a time-of-flight scanner "
                            "reading an oblique surface long?)"}


def most_contradicted(scores: Mapping[str, tuple[float, float]]) -> str | None:
    """The rule for freeing a held intrinsic, written once (the calibration's :func:`most_off`, ``lrfsim plan``'s
    prediction): of :data:`SCALES` in ``scores`` (name -> the value its score test steps to and its sigma), the one
    furthest from its start in sigma, where that is beyond :data:`SCALE_Z_LIMIT`; else None."""
    z = {n: abs(v - BY_NAME[n].start) / s for n, (v, s) in scores.items()
         if n in SCALES and math.isfinite(s) and s > 0}
    name = max(z, key=z.__getitem__, default=None)
    return None if name is None or z[name] <= SCALE_Z_LIMIT else name


def most_off(sol: Solution, max_chi2: float) -> Noted[str] | None:
    """The scale of :data:`SCALES` held at 1 that the data contradict most (its score test on ``sol``,
    Solution.held_score, beyond SCALE_Z_LIMIT sigma), with a note naming the value it steps to; None when none is. One
    at a time, the others tested again once it is free: a gear ratio 2 % off also stepped the range scale beyond 4
    sigma, which it absorbs. None where ``sol``'s reduced chi-square is above ``max_chi2``: a score test means nothing
    where the model does not fit (three times the stated range noise stepped the range scale 4.4 sigma), and the
    chi-square check names that."""
    if not sol.reduced_chi2 <= max_chi2 or (name := most_contradicted(sol.held_score)) is None:
        return None
    value, sigma = sol.held_score[name]
    z = abs(value - BY_NAME[name].start) / sigma
    if BY_NAME[name].unit == "m/rad":  # the incidence bias
        about = f"{value * 1000:.3g} +- {sigma * 1000:.2g} mm/rad ({z:.0f} sigma from 0)"
    else:
        about = f"{value:.5f} +- {sigma:.5f} ({z:.0f} sigma from {BY_NAME[name].start:g})"
    return Noted(name, (f"{SCALES[name]} is off: about {about}: estimated in every solve",))


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


@dataclass(frozen=True)
class Recorded:
    """A recording as the joint solve's choices read it: the recording (its scans and nominal values), its joint
    states (with the servo's direction applied) and the marker returns detected in it."""

    recording: Recording
    joints: JointStates
    detections: Detections


def surfaces_at(at: Solution, markers: MarkerMap, recorded: Recorded, config: JointConfig
                ) -> tuple[list[surfaces.Surface], surfaces.SurfaceReturns]:
    """6b's surfaces chosen at the estimate ``at`` (lrfcal.stages.surfaces.observe_surfaces): the planes the markers
    sit on and the returns on them (every beam but the marker returns), the returns' motor angles at ``at``'s clock
    offset."""
    scans, nominal = recorded.recording.scans, recorded.recording.nominal
    n_beams = scans.ranges_m.shape[1]

    def times_at(i: surfaces.IntArray) -> surfaces.FloatArray:  # beam times of flat indices (K,), elementwise
        return scans.angle_times_at(i // n_beams, i % n_beams)

    on_markers = surfaces.PlaneMarkers(markers.positions_W, nominal.marker_radius_m, max(markers.rms_m, 0.0005))
    selection = surfaces.SurfaceSelection(max_returns=config.surface_max_returns)
    # the motor angles of the beams observe_surfaces reprojects only (elementwise: the same bits as the grid's)
    lambda_at = partial(_motor_angles_at, times_at, recorded.joints, at.clock_offset_s)
    grid = surfaces.ReturnGrid(scans.ranges_m, scans.mu_rad, lambda_at, recorded.detections.labels, times_at)
    return surfaces.observe_surfaces(grid, on_markers, at.params, selection=selection,
                                     intrinsics=at.intrinsic_values)


def unseparated_range_bias(sol: Solution) -> str:
    """Why the range offset and the marker range bias a joint solution ``sol`` estimated are held at 0 instead: not
    separable by this recording (1-sigma beyond lrfcal.estimate.observability.RANGE_BIAS_LIMIT_M); "" when they
    are."""
    if max(sol.range_offset_sigma_m, sol.marker_range_bias_sigma_m) <= observability.RANGE_BIAS_LIMIT_M:
        return ""
    return (f"range offset and marker range bias not separable by this recording (1-sigma "
            f"{sol.range_offset_sigma_m * 1000:.3g} / {sol.marker_range_bias_sigma_m * 1000:.3g} mm): held at 0")


#: why the range offset and the marker range bias are held where no surface returns were found
NO_SURFACE_RANGE_BIAS = ("range offset and marker range bias held at 0: without surface returns the markers alone do "
                         "not separate them from the marker radius and the mount")


def every_plane(ours: Solution, found: tuple[list[surfaces.Surface], surfaces.SurfaceReturns | None],
                recorded: Recorded, config: JointConfig
                ) -> Noted[tuple[list[surfaces.Surface], surfaces.SurfaceReturns]] | None:
    """6b generalised (``config.all_planes``): every other plane of the scene at the joint estimate ``ours``, as free
    planes, after the markers' surfaces ``found``; the surfaces and returns to solve jointly with a note, None when
    the scene shows no other plane."""
    scans, joints, detections = recorded.recording.scans, recorded.joints, recorded.detections
    others, other_planes = scene_plane_returns(scans, joints, ours, detections.labels >= 0, list(found[0]), config)
    if not len(others):
        return None
    return Noted(([*found[0], *other_planes], merge_returns(found[1], others)), (
        f"{len(other_planes)} more planes of the scene ({len(others)} returns) solved jointly as free planes",))


def _motor_angles_at(times_at: Callable[[surfaces.IntArray], surfaces.FloatArray], joints: JointStates,
                     clock_offset_s: float, i: surfaces.IntArray) -> surfaces.FloatArray:
    """The motor angles (K,) of the beams of flat indices ``i`` (K,) at ``clock_offset_s`` (lrfcal.stages.timing)."""
    return timing.motor_angles(times_at(i), joints, clock_offset_s=clock_offset_s, tolerance_s=math.inf)


__all__ = ["NO_SURFACE_RANGE_BIAS", "SCALES", "JointConfig", "SCALE_Z_LIMIT", "Recorded", "every_plane",
           "most_contradicted", "most_off", "surfaces_at", "unseparated_range_bias"]
