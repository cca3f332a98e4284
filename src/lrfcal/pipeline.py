"""The calibration, as in the seed paper's Sec. III and IV-C, one stage per module.

1. markers from tape distances (mds)          5. start: mount pose from that alignment, DH from nominal
2. marker returns in the intensity image      6. Levenberg-Marquardt over the 10 parameters (solve), then
   (detection)                                   jointly with the surfaces the markers sit on (surfaces)
3. per-beam time and motor angle (timing)     7. reprojection of every beam, before and after (reproject)
4. blobs matched to markers (association)     8. tunnel planes and dimensions (geometry)

The paper's own variant (one max-intensity beam per blob, one motor angle per scan) runs beside ours as the
baseline, on the same detections and association, so that the gain is measured.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from . import association, detection, geometry, mds, reproject, solve, surfaces, timing
from .errors import CalibrationError
from .kinematics import PARAM_NAMES, Params, Pose
from .types import CalibrationResult, Observations, Recording, Solution


@dataclass(frozen=True)
class CalibConfig:
    """Options of the calibration (defaults: the UTM-30LX-EW and a hand-taped marker layout)."""

    range_sigma_m: float = 0.010  # UTM-30LX-EW repeatability (its spec sheet)
    association_gate_m: float = 0.05  # blob-to-marker distance accepted after the nominal alignment
    clock_offset_s: float = 0.0  # laser stamp minus servo stamp, if known
    baseline: bool = True  # also run the paper's variant for comparison
    cloud_stride: int = 1  # reproject every n-th scan into the clouds
    geometry: bool = True  # fit tunnel planes (Table III)
    surfaces: bool = True  # use the returns from the planes the markers are mounted on (stage 6b)
    surface_max_returns: int = 40000  # an even subsample of them, for speed


def calibrate(
    recording: Recording, config: CalibConfig | None = None, progress: Callable[[str], None] | None = None
) -> CalibrationResult:
    """Run stages 1-8 on a recording; see the module docstring.

    ``progress(stage)`` is called with the name of each stage as it starts (for a CLI's status line).
    """
    config = config or CalibConfig()
    clock = _Stopwatch(progress)
    scans, joints, nominal = recording.scans, recording.joints, recording.nominal

    markers = mds.marker_map(recording.tape)  # 1.
    clock.lap("mds")

    detections = detection.detect(scans)  # 2.
    if not detections.blobs:
        raise CalibrationError(
            f"no marker returns found (intensity threshold {detections.threshold:.0f} counts)"
        )
    clock.lap("detection")

    returns = detection.observations(scans, joints, detections, clock_offset_s=config.clock_offset_s)  # 3.
    lambda_beams = timing.motor_angles(scans.beam_times_s, joints, clock_offset_s=config.clock_offset_s)
    clock.lap("timing")

    centres_M = detection.blob_centres_M(returns, nominal.dh, nominal.marker_radius_m)  # 4.
    assoc = association.associate(centres_M, markers, gate_m=config.association_gate_m)
    if assoc.mirrored:
        markers = association.unmirror(markers)
    matched = _with_markers(returns, assoc.blob_to_marker)
    if len(np.unique(matched.marker)) < 4:
        raise CalibrationError(
            f"only {len(np.unique(matched.marker))} markers matched to detections (need >= 4); "
            f"alignment RMS {assoc.rms_m * 1000:.1f} mm"
        )
    clock.lap("association")

    start = Params(Pose.from_matrix(assoc.T_W_M), nominal.dh)  # 5.
    fit = partial(solve.solve, markers_W=markers.positions_W, marker_radius_m=nominal.marker_radius_m,
                  range_sigma_m=config.range_sigma_m)
    ours = fit(matched, start=start, model="sphere")  # 6.
    clock.lap("solve")

    surface_list, on_surfaces = [], None
    if config.surfaces:  # 6b. every beam on the markers' planes, jointly with the markers
        surface_list, on_surfaces = surfaces.observe_surfaces(
            scans.ranges_m, scans.mu_rad, lambda_beams, detections.labels, markers.positions_W,
            nominal.marker_radius_m, ours.params, position_sigma_m=max(markers.rms_m, 0.0005),
            max_returns=config.surface_max_returns,
        )
        if len(on_surfaces):
            ours = fit(matched, start=ours.params, model="sphere", surfaces=on_surfaces, planes=surface_list)
        clock.lap("surfaces")
    _check_determined(ours)

    baseline = None
    if config.baseline:  # the paper: the blob's brightest beam, the motor angle at the scan's stamp
        peaks = matched.subset(matched.is_peak)
        lambda_scan = timing.scan_angles(scans, joints, clock_offset_s=config.clock_offset_s)
        peaks = _replace(peaks, lambda_rad=lambda_scan[peaks.scan])
        baseline = fit(peaks, start=start, model="paper")
        clock.lap("baseline")

    # 7.
    (cloud_before, cloud_after), cloud_intensity = reproject.reproject_clouds(
        scans, lambda_beams, (nominal.dh, ours.params.dh), config.cloud_stride
    )
    clock.lap("reprojection")

    geometry_before = geometry_after = None
    if config.geometry:  # 8.
        geometry_before = geometry.tunnel_geometry(cloud_before)
        geometry_after = geometry.tunnel_geometry(cloud_after)
        clock.lap("geometry")

    return CalibrationResult(
        recording=recording,
        markers=markers,
        detections=detections,
        observations=matched,
        association=assoc,
        start=start,
        solution=ours,
        baseline=baseline,
        cloud_before_M=cloud_before,
        cloud_after_M=cloud_after,
        cloud_intensity=cloud_intensity,
        geometry_before=geometry_before,
        geometry_after=geometry_after,
        timings_s=clock.laps,
        surfaces=tuple(surface_list),
        surface_returns=on_surfaces,
    )


#: A DH parameter this uncertain is not calibrated: the marker layout and sweep leave it (nearly) unobservable.
MAX_SIGMA = {"a": 0.02, "alpha": math.radians(2.0), "b": 0.02, "beta": math.radians(2.0)}


def _check_determined(solution: Solution) -> None:
    """Refuse a solution that did not converge or whose DH parameters the data do not determine."""
    if "maximum number of function evaluations" in solution.status:
        raise CalibrationError(f"the solver did not converge ({solution.status})")
    for name, limit in MAX_SIGMA.items():
        sigma = float(solution.sigma[PARAM_NAMES.index(name)])
        if not sigma <= limit:
            raise CalibrationError(
                f"{name} is not determined by this recording (1-sigma {sigma:.3g}, limit {limit:.3g}): the markers "
                "and sweep leave it unobservable (e.g. all markers at one distance along the motor axis)"
            )


def _with_markers(returns: Observations, blob_to_marker: np.ndarray) -> Observations:
    """Label every return with its blob's marker and keep the labelled ones."""
    labelled = _replace(returns, marker=np.asarray(blob_to_marker)[returns.blob])
    return labelled.subset(labelled.marker >= 0)


def _replace(obs: Observations, **arrays: np.ndarray) -> Observations:
    fields = {k: getattr(obs, k) for k in obs.__dataclass_fields__}
    fields.update(arrays)
    return Observations(**fields)


class _Stopwatch:
    """Times the stages; tells ``progress`` which stage comes next (the names in :data:`STAGES`)."""

    def __init__(self, progress: Callable[[str], None] | None = None) -> None:
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()
        self._progress = progress
        self._say(STAGES[0])

    def _say(self, stage: str) -> None:
        if self._progress is not None:
            self._progress(stage)

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._t
        self._t = now
        if name in STAGES and STAGES.index(name) + 1 < len(STAGES):
            self._say(STAGES[STAGES.index(name) + 1])


#: The stages in the order they run, as reported to ``progress`` and in CalibrationResult.timings_s.
STAGES: tuple[str, ...] = ("mds", "detection", "timing", "association", "solve", "surfaces", "baseline",
                           "reprojection", "geometry")
