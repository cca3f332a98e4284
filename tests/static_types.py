"""Type-checked by mypy in tests/test_layout.py (not a test module): what the code's structural types promise.

- lrfcal.config.CalibConfig satisfies every stage's configuration slice (the Protocols of the options a stage
  reads), so each stage can be called with the one validated configuration while naming only what it reads.
- Each way is a ``lrfcal.pipeline.loop.Way`` with its steps' types: what each step returns is what the next one takes,
  and its class what the orchestrator constructs it as (``lrfcal.pipeline.WayOf``).
"""

from __future__ import annotations

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.estimate.checks import CheckConfig
from lrfcal.pipeline import WayOf
from lrfcal.pipeline.loop import Way
from lrfcal.result import Observer
from lrfcal.stages import markers, scene
from lrfcal.stages.alternatives import AlternativesConfig, Start
from lrfcal.stages.joint import JointConfig
from lrfcal.stages.marker_sets import MarkerSets
from lrfcal.stages.matching import MatchConfig
from lrfcal.stages.starts import PlaneSets, PlaneStart
from lrfcal.stages.targetless import SceneConfig, SegmentConfig
from lrfcal.types import JointStates, Recording


def slices(config: CalibConfig) -> tuple[CheckConfig, JointConfig, MatchConfig, SceneConfig, SegmentConfig,
                                         AlternativesConfig, markers.RefineConfig]:
    """``config`` as each slice (mypy rejects the return if CalibConfig lacks an option a slice names, or types it
    otherwise)."""
    return config, config, config, config, config, config, config


def ways(recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch, observer: Observer
         ) -> tuple[Way[markers.Observed, Start, MarkerSets], Way[scene.Scene, PlaneStart, PlaneSets]]:
    """Each way as the Way of its steps' types (mypy rejects the return if a step takes or returns another type)."""
    return (markers.MarkerWay(recording, joints, config, clock, observer),
            scene.PlaneWay(recording, joints, config, clock, observer))


def way_classes() -> tuple[WayOf[markers.Observed, Start, MarkerSets], WayOf[scene.Scene, PlaneStart, PlaneSets]]:
    """Each way's class as the orchestrator takes it (its stages, notes, search, and constructor)."""
    return markers.MarkerWay, scene.PlaneWay
