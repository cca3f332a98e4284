"""Type-checked by mypy in tests/test_layout.py (not a test module): what the code's structural types promise.

- lrfcal.config.CalibConfig satisfies every stage's configuration slice (the Protocols of the options a stage
  reads), so each stage can be called with the one validated configuration while naming only what it reads.
- Each way is a ``lrfcal.pipeline.Way`` with its steps' types: what each step returns is what the next one takes.
"""

from __future__ import annotations

from lrfcal.config import CalibConfig, Stopwatch
from lrfcal.estimate.checks import CheckConfig
from lrfcal.pipeline import Way
from lrfcal.stages import markers, scene
from lrfcal.stages.alternatives import AlternativesConfig
from lrfcal.stages.joint import JointConfig
from lrfcal.stages.matching import MatchConfig
from lrfcal.stages.targetless import SceneConfig, SegmentConfig
from lrfcal.types import JointStates, Recording


def slices(config: CalibConfig) -> tuple[CheckConfig, JointConfig, MatchConfig, SceneConfig, SegmentConfig,
                                         AlternativesConfig, markers.RefineConfig]:
    """``config`` as each slice (mypy rejects the return if CalibConfig lacks an option a slice names, or types it
    otherwise)."""
    return config, config, config, config, config, config, config


def ways(recording: Recording, joints: JointStates, config: CalibConfig, clock: Stopwatch
         ) -> tuple[Way[None, markers.Observed, markers.Started, markers.Refined],
                    Way[scene.Proposal, scene.Scene, scene.Started, scene.Refined]]:
    """Each way as the Way of its steps' types (mypy rejects the return if a step takes or returns another type)."""
    return markers.MarkerWay(recording, joints, config, clock), scene.PlaneWay(recording, joints, config, clock)
