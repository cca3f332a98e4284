"""What both ways of calibrating share (lrfcal.stages.markers, lrfcal.stages.targetless, run by lrfcal.pipeline): the
options and
the stopwatch that reports the stages (the checks are lrfcal.estimate.checks)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from lrfcal.errors import InputError

#: UTM-30LX-EW repeatability (Hokuyo UTM-30LX-EW specification: sigma < 10 mm below 10 m) [m]
DEFAULT_RANGE_SIGMA_M = 0.010
#: returns meeting their plane more obliquely than this are left out by default (CalibConfig.max_incidence_rad;
#: also the DH search's own, lrfcal.stages.propose) [rad]
DEFAULT_MAX_INCIDENCE_RAD = math.radians(65.0)

PositiveFloat = Annotated[float, Field(gt=0.0)]
#: the nominal DH values' 1-sigma when the rig file does not declare it (a, alpha, b, beta [m, rad]): a hand-built
#: rig's centimetre and few degrees (CalibConfig.nominal_tolerance)
DEFAULT_NOMINAL_TOLERANCE = (0.010, math.radians(5.0), 0.010, math.radians(5.0))


class CalibConfig(BaseModel):
    """Options of the calibration (defaults: the UTM-30LX-EW and a hand-taped marker layout), validated with bounds;
    written into calibration.yaml as the effective configuration (``config``).

    Raises:
        InputError: an option out of its bounds (named, with the bound).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    #: the scanner's range noise [m]; None: the rig file's ``range_sigma_m``, else DEFAULT_RANGE_SIGMA_M (resolved
    #: once by :func:`lrfcal.pipeline.calibrate`, so that every stage sees a number)
    range_sigma_m: float | None = Field(None, gt=0.0, le=1.0)
    #: blob-to-marker distance accepted after the nominal alignment [m]
    association_gate_m: float = Field(0.05, gt=0.0, le=10.0)
    #: laser stamp minus servo stamp: the start (prior) of its estimate [s] (checked finite by the pipeline)
    clock_offset_s: float = 0.0
    estimate_clock: bool | None = None  # estimate the clock offset; None: when the sweep goes both ways
    baseline: bool = True  # also run the paper's variant for comparison
    cloud_stride: int = Field(1, ge=1)  # reproject every n-th scan into the clouds
    clouds: bool = True  # reproject the clouds before / after (stage 7; False: empty clouds, no geometry)
    geometry: bool = True  # fit tunnel planes (Table III)
    surfaces: bool = True  # use the returns from the planes the markers are mounted on (stage 6b)
    surface_max_returns: int = Field(40000, ge=100)  # an even subsample of them, for speed
    force: bool = False  # return a result even when a consistency check fails (the failures are recorded)
    #: estimate a constant range offset and a marker-return range bias in the joint solve with the surfaces (the
    #: only data that separate them); held at 0 when the recording does not separate them (1-sigma > 5 mm)
    estimate_range_bias: bool = True
    #: residuals more than 2x the stated noise: the model does not explain the data
    max_reduced_chi2: float = Field(4.0, gt=0.0)
    second_opinion_p: float = Field(1e-3, gt=0.0, lt=1.0)  # false-alarm rate of the second-opinion test
    #: the design-drawing (nominal) DH values' 1-sigma (a, alpha, b, beta [m, rad]); None: the rig file's
    #: ``dh_tolerance``, else DEFAULT_NOMINAL_TOLERANCE (lrfcal.pipeline.calibrate resolves it). Read as
    #: :attr:`nominal_tolerance`; see there for its uses
    dh_tolerance: tuple[PositiveFloat, PositiveFloat, PositiveFloat, PositiveFloat] | None = None
    #: calibrate from the scene's planes without markers (lrfcal.stages.targetless); None: when there are no tape
    #: distances
    targetless: bool | None = None
    plane_returns: int = Field(250000, ge=1000)  # targetless: an even subsample of the returns, for speed
    #: with markers: also calibrate the same recording targetless and show it beside the marker results (report)
    compare_targetless: bool = False
    #: with markers: every other plane of the scene joins the markers' surfaces in the joint solve (free planes)
    all_planes: bool = False
    #: targetless: returns meeting their plane more obliquely than this are left out (the beam's footprint
    #: spreads along the plane and the range reads short) [rad]
    max_incidence_rad: float = Field(DEFAULT_MAX_INCIDENCE_RAD, gt=0.0, le=math.pi / 2)
    #: targetless: estimate the scanner's range error along the scan with the DH (a range offset per bin of beams,
    #: its slowly varying part held; lrfcal.model.range_pattern), a nuisance of the cost like the planes
    range_pattern: bool = False

    def __init__(self, **options: Any) -> None:
        try:
            super().__init__(**options)
        except ValidationError as err:
            e = err.errors()[0]
            where = ".".join(str(x) for x in e["loc"]) or "options"
            raise InputError(f"calibration option {where}: {e['msg']} (got {e.get('input')!r})") from None

    @property
    def nominal_tolerance(self) -> tuple[float, float, float, float]:
        """The nominal DH values' 1-sigma (a, alpha, b, beta [m, rad]; ``dh_tolerance``, else the default): the
        targetless cost's prior on the DH and the held parameters' uncertainty carried into the others (the consider
        covariance, lrfcal.stages.scene), and the scale by which the checks judge a DH estimate's distance from the
        nominal (the mirror image, the servo's direction: lrfcal.estimate.checks)."""
        return DEFAULT_NOMINAL_TOLERANCE if self.dh_tolerance is None else self.dh_tolerance

    def replace(self, **changes: Any) -> CalibConfig:
        """A copy with ``changes``, validated."""
        return CalibConfig(**{**self.model_dump(), **changes})


class Stopwatch:
    """Times the stages; tells ``progress`` which stage comes next (the names in ``stages``, in order)."""

    def __init__(self, progress: Callable[[str], None] | None, stages: tuple[str, ...]) -> None:
        self.stages = stages
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()
        self._progress = progress
        self._say(self.stages[0])

    def _say(self, stage: str) -> None:
        if self._progress is not None:
            self._progress(stage)

    def lap(self, name: str) -> None:
        """Stage ``name`` ended."""
        now = time.perf_counter()
        self.laps[name] = now - self._t
        self._t = now
        if name in self.stages and self.stages.index(name) + 1 < len(self.stages):
            self._say(self.stages[self.stages.index(name) + 1])


__all__ = ["DEFAULT_MAX_INCIDENCE_RAD", "DEFAULT_RANGE_SIGMA_M", "CalibConfig", "Stopwatch"]
