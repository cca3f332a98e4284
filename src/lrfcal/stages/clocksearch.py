"""Where a sweep's two directions see the same scene: a coarse search of the clock offset over the offsets the data
allow, to judge a ``--clock-offset`` start before the solve (issue 46).

The solve finds the clock offset only from a start within a few degrees of motor angle of it (docs/starts.md); from
farther it settles elsewhere, or refuses blaming the markers. A sweep that goes both ways measures the offset
without any model: at the true offset, the scans of the two directions at the same motor angle see the same scene,
so their ranges agree; at a wrong offset tau each direction's angles are off by the sweep's speed times tau, in
opposite senses. :func:`line_up` evaluates that disagreement (the trimmed mean absolute range difference of the scans of
odd passes with the scans of even passes nearest in motor angle, over :data:`BEAMS` beams spread over the scan) on
a grid over the bound the model sets (lrfcal.model.motor.clock_offset_bound_s).

Array shapes: S scans, N beams, J joint-state samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lrfcal.stages.timing import covered_scans, motor_angles, scan_spans, sweep_passes, unwrapped_positions
from lrfcal.types import JointStates, Scans

#: the beams compared per scan, evenly spread over it
BEAMS = 64
#: the share of the smallest range differences averaged (the rest: what one direction sees past an edge that the
#: other does not; a mean, not a median, which the ranges' 1 mm resolution would make tie over many offsets)
TRIMMED = 0.75
#: grid points of the search over [-bound, bound]
GRID = 81
#: a start whose motor angle lies farther than this from where the directions line up is not solved from [rad]
#: (plane_30deg at 45 deg/s: found the offset from 6.8 deg, refused blaming a marker from 9 deg)
MAX_START_ERROR_RAD = math.radians(8.0)
#: ... when the directions agree at least this much better there than at the start (a share of the start's median
#: range difference): a scene that looks alike at every offset (one plane, a tunnel's uniform walls) says nothing
MAX_GAIN_RATIO = 0.7


@dataclass(frozen=True)
class LineUp:
    """The search's outcome: the offset where the directions agree best [s], their range difference
    (:func:`mismatch_m`) there and at the start [m], and the sweep's speed [rad/s] (the median of the moving joint
    states')."""

    offset_s: float
    mismatch_m: float
    start_mismatch_m: float
    speed_rad_s: float

    def start_error_rad(self, start_s: float) -> float:
        """How far [rad] the start's motor angles lie from the lined-up ones (speed times the offsets' difference)."""
        return self.speed_rad_s * abs(start_s - self.offset_s)

    def refutes(self, start_s: float) -> bool:
        """The start is too far to solve from, and the scene says so clearly (MAX_START_ERROR_RAD, MAX_GAIN_RATIO)."""
        return (self.start_error_rad(start_s) > MAX_START_ERROR_RAD
                and self.mismatch_m < MAX_GAIN_RATIO * self.start_mismatch_m)


def mismatch_m(scans: Scans, joints: JointStates, offset_s: float) -> float:
    """The mean of the smallest TRIMMED of the absolute range differences [m] between the scans of odd passes and the
    scans of even passes nearest in motor angle (at the middle of each scan), at clock offset ``offset_s``, over BEAMS
    beams; NaN without both directions or returns to compare."""
    inside = covered_scans(scans, joints, offset_s)
    idx = np.flatnonzero(inside)
    if idx.size < 4:
        return math.nan
    lo, hi = scan_spans(scans)
    lam = motor_angles(0.5 * (lo[idx] + hi[idx]), joints, offset_s, tolerance_s=math.inf)
    passes = sweep_passes(lam)
    even, odd = idx[passes % 2 == 0], idx[passes % 2 == 1]
    if even.size < 2 or odd.size < 1:
        return math.nan
    le_all = lam[passes % 2 == 0]
    order = np.argsort(le_all)
    le = le_all[order]
    lo_ = lam[passes % 2 == 1]
    k = np.clip(np.searchsorted(le, lo_), 1, le.size - 1)
    nearest = np.where(np.abs(le[k - 1] - lo_) <= np.abs(le[k] - lo_), k - 1, k)
    match = even[order][nearest]
    cols = np.unique(np.linspace(0, scans.ranges_m.shape[1] - 1, BEAMS).astype(np.int64))
    d = np.abs(scans.ranges_m[np.ix_(odd, cols)] - scans.ranges_m[np.ix_(match, cols)])
    d = np.sort(d[np.isfinite(d)])
    return float(np.mean(d[: max(1, int(TRIMMED * d.size))])) if d.size else math.nan


def line_up(scans: Scans, joints: JointStates, bound_s: float, start_s: float) -> LineUp | None:
    """The offset within +-``bound_s`` where the two directions agree best (module docstring), or None when the
    sweep does not go both ways, the rig steps and scans (its angle is the scan's own), or nothing compares."""
    if scans.angle_per_scan or scans.stamps_s.size < 4:
        return None
    grid = np.linspace(-bound_s, bound_s, GRID)
    costs = np.array([mismatch_m(scans, joints, float(t)) for t in grid])
    at_start = mismatch_m(scans, joints, start_s)
    if not np.any(np.isfinite(costs)) or not math.isfinite(at_start):
        return None
    best = int(np.nanargmin(costs))
    q, t = unwrapped_positions(joints), joints.stamps_s
    rate = np.abs(np.diff(q)) / np.maximum(np.diff(t), 1e-9)
    moving = rate[rate > 1e-3]
    speed = float(np.median(moving)) if moving.size else 0.0
    return LineUp(float(grid[best]), float(costs[best]), at_start, speed)


__all__ = ["BEAMS", "GRID", "MAX_GAIN_RATIO", "MAX_START_ERROR_RAD", "LineUp", "line_up", "mismatch_m"]
