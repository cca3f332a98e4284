"""What a calibration returns: the result, typed by its evidence.

Both ways of calibrating (lrfcal.pipeline chooses one) return a :class:`CalibrationResult` with what both have (the
recording, the start, the solution, the clouds, the tunnel geometry, the checks, the notes, the methods side by side,
the configuration, the timings, the servo direction) and the evidence it rests on, one of two types:

- :class:`MarkerEvidence`: with markers (lrfcal.stages.markers): the marker map from the tape, the intensity blobs,
  the marker returns and their association, the paper's baseline, the surfaces the markers sit on and their returns;
- :class:`PlaneEvidence`: from the scene's planes alone (lrfcal.stages.targetless): the planes, their flatness
  before and after, the parameters held, and the plane returns solved on.

Who reads a result dispatches on the type of its evidence (``match result.evidence: case MarkerEvidence() as ev``),
never on optional fields: a marker result always has its markers, a targetless one never has any.
Array shapes as in lrfcal.types: K marker returns, P planes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from lrfcal.config import CalibConfig
from lrfcal.model.kinematics import Params
from lrfcal.types import (
    Association,
    Check,
    Detections,
    FloatArray,
    MarkerMap,
    Observations,
    Recording,
    Scans,
    ScenePlane,
    Solution,
    Surface,
    SurfaceReturns,
    TunnelGeometry,
)


@dataclass(frozen=True)
class PlaneFit:
    """What the targetless calibration found and used: the scene's planes (frame M, as segmented at the rig file's
    DH), each plane's thickness (RMS distance of its returns from their best-fit plane, m) and best-fit normal (P, 3)
    with the nominal and with the calibrated DH, the parameters held at nominal (with why), and the start whose
    minimum of the cost is the estimate ("the rig file's DH", "the DH search's proposal", ...)."""

    planes: tuple[ScenePlane, ...]
    rms_before_m: FloatArray
    rms_after_m: FloatArray
    n_returns: NDArray[np.int64]
    held: tuple[str, ...]
    held_reason: str
    start: str
    normals_before: FloatArray
    normals_after: FloatArray


@dataclass(frozen=True)
class MarkerEvidence:
    """What a calibration with markers rests on (lrfcal.stages.markers.MarkerWay): the marker map from the tape,
    the intensity blobs, the marker returns solved on (K rows; scan indices into the result's ``recording.scans``)
    and the blobs' association with the map; the paper's method on the same returns (``baseline``: blob peaks, one
    motor angle per scan; None when not run); the planes the markers are mounted on and the surface returns solved
    jointly with the markers (None when none were)."""

    METHOD: ClassVar[str] = "markers"

    markers: MarkerMap
    detections: Detections
    observations: Observations
    association: Association
    baseline: Solution | None = None
    surfaces: tuple[Surface, ...] = ()
    surface_returns: SurfaceReturns | None = None

    def marker_counts(self) -> NDArray[np.int64]:
        """(n,) the number of returns the solution used on each marker of the map."""
        n = len(self.markers.marker_ids)
        m = np.asarray(self.observations.marker, dtype=np.int64)
        return np.bincount(m[m >= 0], minlength=n)[:n]


@dataclass(frozen=True)
class PlaneEvidence:
    """What a targetless calibration rests on (lrfcal.stages.scene.PlaneWay): the scene's planes and their
    flatness (:class:`PlaneFit`), and the plane returns of the last segmentation, solved on."""

    METHOD: ClassVar[str] = "targetless"

    plane_fit: PlaneFit
    returns: SurfaceReturns


#: the evidence a calibration rests on: one of the two ways
Evidence = MarkerEvidence | PlaneEvidence


@dataclass(frozen=True)
class CalibrationResult:
    """Everything the pipeline produced, for the writers, the loop and the visualisation: what both ways have, and
    the ``evidence`` of the way taken (:class:`MarkerEvidence` or :class:`PlaneEvidence`)."""

    #: the recording as calibrated: its scans are those the joint states cover (the scans trimmed at the ends are
    #: not here), so that scan indices of the evidence's detections and returns index ``recording.scans``
    recording: Recording
    evidence: Evidence
    start: Params
    solution: Solution
    #: the clouds reprojected in M with the start's and with the calibrated DH (Q, 3), their intensities (Q,), and
    #: the tunnel's dimensions in each: made by the pipeline's last step (empty and None until then)
    cloud_before_M: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    cloud_after_M: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    cloud_intensity: FloatArray = field(default_factory=lambda: np.zeros(0))
    geometry_before: TunnelGeometry | None = None
    geometry_after: TunnelGeometry | None = None
    timings_s: dict[str, float] = field(default_factory=dict)
    checks: tuple[Check, ...] = ()  # the consistency checks and their outcome
    notes: tuple[str, ...] = ()  # what the calibration assumed, trimmed or dropped, in words
    #: the DH estimates of the methods run on this recording, by name (markers only, markers and their surfaces,
    #: targetless), shown side by side in the report
    side_by_side: dict[str, Solution] = field(default_factory=dict)
    config: CalibConfig | None = None  # the effective configuration (lrfcal.pipeline resolves its defaults)
    servo_sign: int = 1  # the servo direction used: +1 as declared, -1 negated (only with --force on an ambiguity)

    @property
    def method(self) -> str:
        """How the result was found, as written in calibration.yaml: its evidence's name, "markers"
        (lrfcal.stages.markers) or "targetless" (lrfcal.stages.targetless)."""
        return self.evidence.METHOD


@dataclass(frozen=True)
class Matched:
    """The marker way's blobs matched to the marker map, as its alternative is chosen (before the refinement): the
    scans, the blobs, the association and the marker map (in its handedness), for the intensity figure drawn while
    the refinement goes on."""

    scans: Scans
    detections: Detections
    association: Association
    markers: MarkerMap


class Observer:
    """What a calibration tells whoever runs it while it goes on (lrfcal.pipeline.calibrate's ``observer``): here
    the stages to ``progress`` (None: nothing), and nothing else; a command's subclass also draws the report's figures
    meanwhile (lrfcal.commands.calibration_run). The method does not wait for it nor read anything back."""

    def __init__(self, progress: Callable[[str], None] | None = None) -> None:
        self._progress = progress

    def stage(self, name: str) -> None:
        """The stage ``name`` begins (the way's STAGES, in order): told to ``progress``."""
        if self._progress is not None:
            self._progress(name)

    def matched(self, matched: Matched) -> None:
        """The marker way chose its alternative: its blobs matched to the marker map."""

    def fitted(self, result: CalibrationResult) -> None:
        """The result passed its checks, before its clouds are made (drawn meanwhile: the figures that need none)."""


__all__ = ["CalibrationResult", "Evidence", "MarkerEvidence", "Matched", "Observer", "PlaneEvidence", "PlaneFit"]
