"""Type-checked by mypy in tests/test_layout.py (not a test module): lrfcal.config.CalibConfig satisfies every
stage's configuration slice structurally (the Protocols of the options a stage reads), so each stage can be called
with the one validated configuration while naming only what it reads."""

from __future__ import annotations

from lrfcal.config import CalibConfig
from lrfcal.estimate.checks import CheckConfig
from lrfcal.stages.joint import JointConfig
from lrfcal.stages.matching import MatchConfig
from lrfcal.stages.starts import StartsConfig
from lrfcal.stages.targetless import SceneConfig, SegmentConfig


def slices(config: CalibConfig) -> tuple[CheckConfig, JointConfig, MatchConfig, StartsConfig, SceneConfig,
                                         SegmentConfig]:
    """``config`` as each slice (mypy rejects the return if CalibConfig lacks an option a slice names, or types it
    otherwise)."""
    return config, config, config, config, config, config
