"""lrfcal: calibration of a rotating 2D laser range finder (a servo-turned scanner), with markers (the seed paper's
method) or from the scene's planes.

The public API: what other code (lrfsim, benchmarks, a user's script) may use. Everything else in lrfcal is internal
and may move. Besides this module, other code may import :mod:`lrfcal.model` (the rig model), :mod:`lrfcal.io`
(reading recordings and writing files) and :mod:`lrfcal.errors`.

- calibrate: :func:`calibrate` a :class:`Recording` (read with :func:`read_recording`) with a :class:`CalibConfig`;
  :func:`calibrate_folder` does it for a recording folder and writes the results, as ``lrfcal calibrate`` does;
- check a saved calibration against a new recording: :func:`check_recording` (``lrfcal check``), its
  :class:`CheckOutcome` and :class:`DriftTest`, and the smallest drift a check detects (:func:`detectable_drift`);
- the results: :class:`CalibrationResult`, typed by its evidence (:class:`MarkerEvidence` or :class:`PlaneEvidence`,
  with its :class:`PlaneFit`), :class:`Solution`, :class:`TunnelGeometry`, and the data they hold;
- what ``plan`` needs to predict accuracy without calibrating: the information of marker and surface returns at
  given parameters (:func:`information_at` and its error terms), the observability verdict (:func:`analyse`), the
  marker map's covariance (:func:`map_covariance`), the surfaces the markers sit on (:func:`observe_surfaces`);
- the runtime policies the programs and their worker processes apply (BLAS threads, memory, cores);
- what the two command lines share (lrfsim's too): the typer app (:func:`make_app`, :class:`Command`,
  :func:`run_app`, :data:`QuietOpt`, :func:`finite_between`) and the progress display (:func:`progress_display`).

Names are imported when first used (PEP 562), so ``import lrfcal`` costs nothing: ``lrfcal --help`` imports
neither scipy nor mujoco.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from lrfcal.errors import CalibrationError, InputError, LrfError

__version__ = "0.1.0"

#: public name -> the module that defines it
_EXPORTS: dict[str, str] = {
    # calibrating
    "calibrate": "lrfcal.pipeline",
    "STAGES": "lrfcal.pipeline",
    "Observer": "lrfcal.result",
    "CalibConfig": "lrfcal.config",
    "DEFAULT_RANGE_SIGMA_M": "lrfcal.config",
    "calibrate_folder": "lrfcal.commands.calibrate",
    "viewer_can_spawn": "lrfcal.commands.calibrate",
    "read_recording": "lrfcal.io.recording",
    # checking a calibration against a new recording (lrfcal check; lrfsim's drift study and plan)
    "check_recording": "lrfcal.commands.check",
    "CheckOutcome": "lrfcal.commands.check",
    "DriftTest": "lrfcal.estimate.drift",
    "DEFAULT_FALSE_ALARM": "lrfcal.estimate.drift",
    "detectable_drift": "lrfcal.estimate.drift",
    # the rig model's parameters
    "DH": "lrfcal.model.kinematics",
    "PARAM_NAMES": "lrfcal.model.kinematics",
    "Params": "lrfcal.model.kinematics",
    "Pose": "lrfcal.model.kinematics",
    # the data and the results
    "Recording": "lrfcal.types",
    "Scans": "lrfcal.types",
    "JointStates": "lrfcal.types",
    "Observations": "lrfcal.types",
    "CalibrationResult": "lrfcal.result",
    "MarkerEvidence": "lrfcal.result",
    "PlaneEvidence": "lrfcal.result",
    "PlaneFit": "lrfcal.result",
    "Solution": "lrfcal.types",
    "TunnelGeometry": "lrfcal.types",
    "print_summary": "lrfcal.report.summary",
    # predicting accuracy (lrfsim plan)
    "information_at": "lrfcal.estimate.information",
    "estimated": "lrfcal.estimate.information",
    "correlation_error_at": "lrfcal.estimate.information",
    "map_error_at": "lrfcal.estimate.information",
    "model_error_at": "lrfcal.estimate.information",
    "lateral_scatter_at": "lrfcal.estimate.information",
    "held_steps_at": "lrfcal.estimate.information",
    "turning_error_at": "lrfcal.estimate.information",
    "scaled_pinv": "lrfcal.estimate.information",
    "LIMITS": "lrfcal.estimate.observability",
    "Observability": "lrfcal.estimate.observability",
    "analyse": "lrfcal.estimate.observability",
    "Verdict": "lrfcal.estimate.observability",
    "mirror_check": "lrfcal.estimate.checks",
    "of_covariance": "lrfcal.estimate.observability",
    "map_covariance": "lrfcal.stages.mds",
    "SCALES": "lrfcal.stages.joint",
    "SCALE_Z_LIMIT": "lrfcal.stages.joint",
    "most_contradicted": "lrfcal.stages.joint",
    "OnPlanes": "lrfcal.estimate.problem",
    "Surface": "lrfcal.types",
    "PlaneMarkers": "lrfcal.stages.surfaces",
    "ReturnGrid": "lrfcal.stages.surfaces",
    "SurfaceSelection": "lrfcal.stages.surfaces",
    "SurfaceReturns": "lrfcal.types",
    "observe_surfaces": "lrfcal.stages.surfaces",
    "detect": "lrfcal.stages.detection",
    # the runtime policies
    "apply_thread_policy": "lrfcal.runtime.threads",
    "call_with_thread_policy": "lrfcal.runtime.threads",
    "one_blas_thread": "lrfcal.runtime.threads",
    "apply_memory_policy": "lrfcal.runtime.memory",
    "keep_freed_memory": "lrfcal.runtime.memory",
    "cores": "lrfcal.runtime.forked",
    # the command lines' shared parts (lrfsim's too): the typer app, its errors as one line, the progress display
    "Command": "lrfcal.terminal.cliutil",
    "QuietOpt": "lrfcal.terminal.cliutil",
    "finite_between": "lrfcal.terminal.cliutil",
    "make_app": "lrfcal.terminal.cliutil",
    "run_app": "lrfcal.terminal.cliutil",
    "progress_display": "lrfcal.terminal.progress",
}

__all__ = ["CalibConfig", "CalibrationError", "CalibrationResult", "CheckOutcome", "Command", "DEFAULT_FALSE_ALARM",
           "DEFAULT_RANGE_SIGMA_M", "DH", "DriftTest", "check_recording", "detectable_drift",
           "InputError", "JointStates", "LIMITS", "LrfError", "MarkerEvidence", "Observability", "Observations",
           "Observer", "OnPlanes", "PARAM_NAMES", "Params", "PlaneEvidence", "PlaneFit", "PlaneMarkers", "Pose",
           "QuietOpt", "Recording", "ReturnGrid", "SCALES", "SCALE_Z_LIMIT", "STAGES", "Scans", "Solution", "Surface",
           "SurfaceReturns", "SurfaceSelection", "TunnelGeometry", "Verdict", "analyse", "apply_memory_policy",
           "apply_thread_policy", "calibrate", "calibrate_folder", "call_with_thread_policy", "cores",
           "correlation_error_at", "detect", "estimated", "finite_between", "held_steps_at", "information_at",
           "keep_freed_memory", "lateral_scatter_at", "make_app", "map_covariance", "map_error_at", "mirror_check",
           "model_error_at", "most_contradicted", "observe_surfaces", "of_covariance", "one_blas_thread",
           "print_summary", "progress_display", "read_recording", "run_app", "scaled_pinv", "turning_error_at",
           "viewer_can_spawn"]


def __getattr__(name: str) -> Any:
    """The public name ``name``, imported from its module when first asked for."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'lrfcal' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if TYPE_CHECKING:  # the same names for type checkers and editors
    from lrfcal.commands.calibrate import calibrate_folder, viewer_can_spawn
    from lrfcal.commands.check import CheckOutcome, check_recording
    from lrfcal.config import DEFAULT_RANGE_SIGMA_M, CalibConfig
    from lrfcal.estimate.checks import mirror_check
    from lrfcal.estimate.drift import DEFAULT_FALSE_ALARM, DriftTest, detectable_drift
    from lrfcal.estimate.information import (
        correlation_error_at,
        estimated,
        held_steps_at,
        information_at,
        lateral_scatter_at,
        map_error_at,
        model_error_at,
        scaled_pinv,
        turning_error_at,
    )
    from lrfcal.estimate.observability import LIMITS, Observability, Verdict, analyse, of_covariance
    from lrfcal.estimate.problem import OnPlanes
    from lrfcal.io.recording import read_recording
    from lrfcal.model.kinematics import DH, PARAM_NAMES, Params, Pose
    from lrfcal.pipeline import STAGES, calibrate
    from lrfcal.report.summary import print_summary
    from lrfcal.result import CalibrationResult, MarkerEvidence, Observer, PlaneEvidence, PlaneFit
    from lrfcal.runtime.forked import cores
    from lrfcal.runtime.memory import apply_memory_policy, keep_freed_memory
    from lrfcal.runtime.threads import apply_thread_policy, call_with_thread_policy, one_blas_thread
    from lrfcal.stages.detection import detect
    from lrfcal.stages.joint import SCALE_Z_LIMIT, SCALES, most_contradicted
    from lrfcal.stages.mds import map_covariance
    from lrfcal.stages.surfaces import PlaneMarkers, ReturnGrid, SurfaceSelection, observe_surfaces
    from lrfcal.terminal.cliutil import Command, QuietOpt, finite_between, make_app, run_app
    from lrfcal.terminal.progress import progress_display
    from lrfcal.types import (
        JointStates,
        Observations,
        Recording,
        Scans,
        Solution,
        Surface,
        SurfaceReturns,
        TunnelGeometry,
    )
