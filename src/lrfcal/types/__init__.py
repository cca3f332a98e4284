"""The data passed between the stages, the estimate and the result: pure containers, no I/O, no computation beyond
properties and the two spans the readers and the stages share (:func:`scan_spans`, :func:`joint_period_s`).

Below the estimate, the stages and the readers, which all take them from here (docs/architecture.md): a recording
(:mod:`.recording`: Scans, JointStates, TapeMeasurements, Nominal, Recording, the reader's ReadReport) and where a
bag keeps its data (:mod:`.sources`: the rig file's ScanSource, ServoSource, TfSource and LogLayout); the marker
way's map, blobs, returns and association (:mod:`.markers`); the surfaces and planes observed (:mod:`.surfaces`);
a solve's Solution with its Levenberg-Marquardt Iterations, a Check, a stage's Noted result (:mod:`.solution`);
what the orchestrator's loop passes between a way's steps, a Fit and a start Tried (:mod:`.fit`);
the array types (:mod:`.arrays`). Every name is importable from ``lrfcal.types`` itself.

Array shapes: S scans, N beams per scan, J joint-state samples, n markers, P measured pairs, B blobs,
K marker returns (observations), K2 surface returns.
"""

from __future__ import annotations

from lrfcal.types.arrays import BoolArray, FloatArray, IntArray
from lrfcal.types.fit import Fit, Refusal, Tried
from lrfcal.types.markers import Association, Blob, Detections, DroppedPair, Labels, MarkerMap, Observations
from lrfcal.types.recording import (
    JointStates,
    Nominal,
    ReadReport,
    Recording,
    Scans,
    SelfBox,
    TapeMeasurements,
    joint_period_s,
    scan_spans,
)
from lrfcal.types.solution import Check, Iteration, Noted, PlanePulls, Solution, Spread
from lrfcal.types.sources import LogLayout, ScanSource, ServoSource, TfSource
from lrfcal.types.surfaces import Plane, ScenePlane, Surface, SurfaceReturns, TunnelGeometry

__all__ = ["Association", "Blob", "BoolArray", "Check", "Detections", "DroppedPair", "Fit", "FloatArray", "IntArray",
           "Iteration", "JointStates", "Labels", "LogLayout", "MarkerMap", "Nominal", "Noted", "Observations", "Plane",
           "PlanePulls", "ReadReport", "Recording", "Refusal", "ScanSource", "Scans", "ScenePlane", "SelfBox",
           "ServoSource", "Solution", "Spread", "Surface", "SurfaceReturns", "TapeMeasurements", "TfSource", "Tried",
           "TunnelGeometry", "joint_period_s", "scan_spans"]
