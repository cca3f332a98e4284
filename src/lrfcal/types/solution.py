"""What a solve returns and what the checks say: the estimate with its uncertainty, the Levenberg-Marquardt
iterations it took, the covariance's parts, a check's verdict, and a stage's result with its notes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import ESTIMATE_NAMES, Params
from lrfcal.model.unknowns import DH_SLICE
from lrfcal.types.arrays import BoolArray, FloatArray


@dataclass(frozen=True)
class PlanePulls:
    """Each plane's pull on a solution (lrfcal.estimate.influence): over the estimated core unknowns ``names`` (c,),
    the returns of each of the P planes (P,), the estimate without the plane's returns minus the estimate (one
    Gauss-Newton step) (P, c), that difference's covariance by the noise alone (P, c, c) (NaN where the others with
    the dense rows determine nothing) and the 1-sigma the other planes alone give (P, c) (the dense rows, the design
    drawing's prior, left out; inf where they do not determine every unknown), on the scale of the Spread's
    statistical covariance."""

    names: tuple[str, ...]
    returns: NDArray[np.int64]
    shift: FloatArray
    difference: FloatArray
    others: FloatArray


@dataclass(frozen=True)
class Spread:
    """What the covariance of the difference of two solutions of overlapping data is made of (lrfcal.estimate.checks):
    each
    cluster's id (C,) and influence (J^T J)^-1 J_c^T r_c over the core unknowns (C, N_CORE), and the statistical
    covariance max(s^2, 1) (J^T J)^-1 (N_CORE, N_CORE), before any widening (NaN where held or with rank loss); and
    each plane's pull (the solution without one plane's returns, :class:`PlanePulls`; None without planes)."""

    ids: NDArray[np.int64]
    influence: FloatArray
    statistical: FloatArray
    planes: PlanePulls | None = None


@dataclass(frozen=True)
class Iteration:
    """One accepted Levenberg-Marquardt iteration (as mujoco's ``minimize.IterLog``): the (Huber) cost 0.5 sum r^2
    after the step, the step's largest ratio to its unknown's sigma, the damping it was taken with, and the
    evaluations of the residuals so far."""

    cost: float
    step_sigma: float
    damping: float
    evaluations: int


@dataclass(frozen=True)
class Solution:
    """Stage 6: the estimate and its uncertainty.

    covariance (10, 10) and sigma (10,) in kinematics.ESTIMATE_NAMES order (x, y, z, the mount rotation as a
    rotation vector rx, ry, rz in frame M, a, alpha, b, beta; NaN for parameters held fixed, inf where the data do
    not determine them); residual_rms_m: RMS of the 3D residuals of the returns kept; residuals_m (K, 3): reprojected
    return minus its model point in W; per-marker RMS (n,); clock offset (laser stamp - servo stamp) and its sigma
    (NaN when held); information (k, k): the marginal information over ``information_names`` (the estimated core
    unknowns, lrfcal.model.unknowns.CORE_NAMES); chi (K,): whitened residual per return (NaN for unused rows);
    inlier (K,): returns kept; lambda_rad (K,): the motor angle of each return at the estimated clock offset."""

    params: Params
    covariance: FloatArray
    sigma: FloatArray
    residual_rms_m: float
    residuals_m: FloatArray
    per_marker_rms_m: FloatArray
    n_observations: int
    n_iterations: int
    status: str
    clock_offset_s: float = 0.0
    clock_offset_sigma_s: float = float("nan")
    information: FloatArray | None = None
    information_names: tuple[str, ...] = ()
    reduced_chi2: float = float("nan")
    converged: bool = True
    chi: FloatArray | None = None
    inlier: BoolArray | None = None
    lambda_rad: FloatArray | None = None
    n_surface_returns: int = 0
    #: every intrinsic of the rig model (lrfcal.model.unknowns.INTRINSICS): name -> (value, sigma; NaN when held)
    intrinsics: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: every unknown held by default that this solve held: name -> (the value one Gauss-Newton step with it freed
    #: reaches, its 1-sigma) (the score test of lrfcal.estimate.covariance.held_score)
    held_score: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: (10, 3n): how the estimate moves with the marker map's coordinates (lrfcal.estimate.covariance.uncertainty); the
    #: covariance holds the map's part, G C_map G^T (None: the map was taken as exact)
    map_sensitivity: FloatArray | None = None
    #: each cluster's influence and the statistical covariance (Spread, lrfcal.estimate.covariance), for the second
    #: opinion's
    #: covariance of the difference of two solutions (lrfcal.estimate.checks.difference_covariance); None with rank loss
    spread: Spread | None = None
    #: each accepted Levenberg-Marquardt iteration of every pass (lrfcal.estimate.engine.Estimate.log)
    iterations: tuple[Iteration, ...] = ()
    #: the range noise's correlation between neighbouring beams as the marker returns' residuals show it, and the
    #: neighbouring pairs it is measured from (0, 0: no marker returns); the covariance holds it where it counts
    #: (lrfcal.model.noise.shown)
    range_correlation: tuple[float, int] = (0.0, 0)

    @property
    def dh_sigma(self) -> FloatArray:
        """(4,) the DH parameters' 1-sigma (a, alpha, b, beta; NaN where held): the DH block of :attr:`sigma`."""
        return self.sigma[DH_SLICE]

    def estimated_covariance(self) -> tuple[tuple[str, ...], FloatArray]:
        """(names, covariance (k, k)) of every unknown this solution estimated with a finite sigma, in the solver's
        order (lrfcal.model.unknowns.CORE_NAMES: the mount as x, y, z, rx, ry, rz, the DH, the clock offset, the
        intrinsics), with their cross terms: the inverse of :attr:`information` (the covariance the solve reported,
        widened for shared errors and the marker map), its mount and DH block replaced by :attr:`covariance`'s,
        which holds what was added after the solve (a model error between two defensible models, the held
        parameters' tolerance: ``with_dh_systematic``, targetless's consider term), the cross terms kept (adding a
        positive semi-definite part to a block keeps the whole positive semi-definite). Without the information
        (a solution made by hand), the diagonal of the sigmas alone. ``((), (0, 0))`` when nothing is finite."""
        sig = {n: float(s) for n, s in zip(ESTIMATE_NAMES, np.asarray(self.sigma, dtype=float).reshape(-1),
                                            strict=False)}
        sig["clock_offset"] = float(self.clock_offset_sigma_s)
        sig.update({n: float(s) for n, (_, s) in self.intrinsics.items()})
        info_names = tuple(self.information_names)
        if self.information is not None and info_names and np.all(np.isfinite(self.information)):
            info = np.asarray(self.information, dtype=float)
            try:
                col = np.sqrt(np.maximum(np.diag(info), 1e-300))
                base = np.linalg.inv(info / np.outer(col, col)) / np.outer(col, col)
            except np.linalg.LinAlgError:
                base = None
        else:
            base = None
        if base is None:
            names = tuple(n for n in (*ESTIMATE_NAMES, "clock_offset", *self.intrinsics)
                          if math.isfinite(sig.get(n, math.nan)) and sig[n] > 0)
            return names, np.diag([sig[n] ** 2 for n in names])
        cov = np.asarray(self.covariance, dtype=float)
        for i, a in enumerate(info_names):
            for j, b in enumerate(info_names):
                if a in ESTIMATE_NAMES and b in ESTIMATE_NAMES:
                    v = cov[ESTIMATE_NAMES.index(a), ESTIMATE_NAMES.index(b)]
                    if math.isfinite(v):
                        base[i, j] = v
        keep = [i for i, n in enumerate(info_names) if math.isfinite(base[i, i]) and base[i, i] > 0
                and math.isfinite(sig.get(n, math.nan))]
        return tuple(info_names[i] for i in keep), base[np.ix_(keep, keep)]

    @property
    def intrinsic_values(self) -> dict[str, float]:
        """The intrinsics' values by name, estimated or held (what lrfcal.model.unknowns.core_vector takes)."""
        return {name: value for name, (value, _) in self.intrinsics.items()}

    @property
    def range_offset_m(self) -> float:
        """Added to every reported range (estimated with estimate_range_bias; 0 when held)."""
        return self.intrinsics.get("range_offset", (0.0, math.nan))[0]

    @property
    def range_offset_sigma_m(self) -> float:
        """Its 1-sigma, NaN when held."""
        return self.intrinsics.get("range_offset", (0.0, math.nan))[1]

    @property
    def marker_range_bias_m(self) -> float:
        """Added to the ranges of marker returns only."""
        return self.intrinsics.get("marker_range_bias", (0.0, math.nan))[0]

    @property
    def marker_range_bias_sigma_m(self) -> float:
        """Its 1-sigma, NaN when held."""
        return self.intrinsics.get("marker_range_bias", (0.0, math.nan))[1]


@dataclass(frozen=True)
class Check:
    """One consistency check of the result: its name, whether it passed, and the numbers."""

    name: str
    passed: bool
    detail: str


T = TypeVar("T")


@dataclass(frozen=True)
class Noted(Generic[T]):
    """A stage's result ``value`` with its ``notes``: what it assumed, trimmed or dropped, in words, in the order
    they arose (the way and the orchestrator collect them into CalibrationResult.notes)."""

    value: T
    notes: tuple[str, ...] = ()


__all__ = ["Check", "Iteration", "Noted", "Solution", "Spread"]
