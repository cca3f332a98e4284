"""What a simulation produces (lrfsim.simulation.simulate), apart from how: the ground truth, the run's costs and
checks, and the recording's arrays. Its own module so that the stages that read or change a result
(lrfsim.simulation.faults, lrfsim.simulation.recording) need not import the simulator."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import DH, Pose
from lrfsim.sensors.servo import JointSamples
from lrfsim.sensors.tape import TapeResult

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SimTruth:
    """The ground truth of a recording (ground_truth.yaml): true DH and mount T_W_M, marker centres (n, 3)
    in W ((0, 3) without markers), marker radius (None without markers), clock offset (laser - servo), the
    tunnel's dimensions (or None) and the systematic range errors switched on (:func:`systematic_truth`; None
    when all are off)."""

    dh: DH
    mount: Pose
    marker_ids: tuple[str, ...]
    markers_W: FloatArray
    marker_radius_m: float | None
    clock_offset_s: float
    tunnel: dict[str, float] | None
    systematic: dict[str, float] | None = None


@dataclass(frozen=True)
class SimStats:
    """Costs and numerical checks of a run (see lrfsim.sensors.lidar for the batching errors)."""

    n_rays: int
    n_calls: int
    cast_time_s: float
    lidar_time_s: float
    total_time_s: float
    max_origin_error_m: float
    max_direction_error_rad: float
    max_parallax_correction_m: float

    @property
    def rays_per_s(self) -> float:
        return self.n_rays / self.lidar_time_s if self.lidar_time_s > 0 else float("nan")


@dataclass(frozen=True)
class SimResult:
    """Everything a recording holds, as arrays. S scans, N beams, J joint states.

    scan_stamps_s (S,): time of beam 0 on the laser clock; mu_rad (N,); ranges_m (S, N) (no return: NaN or
    +inf); intensities (S, N) counts; beam_lambda_rad (S, N): true motor angle at every beam (truth);
    joints: the JointState stream (servo clock); tape; truth; stats; faults: what lrfsim.simulation.faults injected
    (ground_truth.yaml ``faults``; empty without faults); echo_ranges_m, echo_intensities (S, N, E): the
    multi-echo returns nearest first (NaN: no echo), None unless sensor.echoes.enabled;
    declared_angle_increment_rad: the angle_increment the LaserScan messages declare (None: the sensor's, the true
    one; lrfsim.simulation.faults changes it, the beams stay where they are).
    """

    name: str
    scan_stamps_s: FloatArray
    mu_rad: FloatArray
    ranges_m: FloatArray
    intensities: FloatArray
    beam_lambda_rad: FloatArray
    joints: JointSamples
    tape: TapeResult
    truth: SimTruth
    stats: SimStats
    duration_s: float
    faults: dict[str, Any] = field(default_factory=dict)
    echo_ranges_m: FloatArray | None = None
    echo_intensities: FloatArray | None = None
    declared_angle_increment_rad: float | None = None


__all__ = ["SimResult", "SimStats", "SimTruth"]
