"""The keyword front-end of the one estimate, for callers outside a calibration's orchestrator (``plan``, ``study``,
the tests): :func:`solve`, the marker calibration (marker returns, optionally with surface returns on their planes).
It builds its request (lrfcal.estimate.request: what to estimate, and how it is posed to the engine and reported)
and solves it
(lrfcal.estimate.engine.solved), as the orchestrator (lrfcal.pipeline) does with the requests the stages build.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.estimate.engine import solved
from lrfcal.estimate.request import (
    DEFAULT_OPTIONS,
    DEFAULT_PLANE_OPTIONS,
    MarkerRequest,
    OnPlanes,
    PlaneOptions,
    SolveOptions,
    plane_free,
)
from lrfcal.model.kinematics import Params
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.motor import NO_CLOCK, Clock, MotorClock
from lrfcal.model.unknowns import CORE_NAMES, pack
from lrfcal.types import MarkerMap, Observations, Solution

FloatArray = NDArray[np.float64]


def solve(
    obs: Observations,
    markers_W: ArrayLike | MarkerMap,
    start: Params,
    *,
    sensor: MarkerSensor,
    surfaces: OnPlanes | None = None,
    clock: Clock = NO_CLOCK,
    options: SolveOptions = DEFAULT_OPTIONS,
) -> Solution:
    """Estimate the 10 parameters (and the clock offset, the intrinsics) from marker returns: the
    lrfcal.estimate.request.MarkerRequest of these arguments (its docstring), solved.

    Raises:
        CalibrationError: fewer than 4 usable returns or fewer than 3 distinct markers.
    """
    markers = markers_W if isinstance(markers_W, MarkerMap) else np.asarray(markers_W, dtype=float)
    return solved(MarkerRequest(obs, markers, start, sensor, surfaces, clock, options))


__all__ = ["CORE_NAMES", "DEFAULT_OPTIONS", "DEFAULT_PLANE_OPTIONS", "Clock", "MotorClock", "OnPlanes", "PlaneOptions",
           "SolveOptions", "pack", "plane_free", "solve"]
