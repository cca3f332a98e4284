"""Discrete ambiguities found, not landed on: another minimum of the marker calibration, and a likelihood-ratio test.

The chain's exact twins (lrfcal.model.kinematics.dh_twins) are handled where they arise: the "turned" one is the
same rig (the canonical DH branch, lrfcal.model.chart), the mirror images explain the data exactly with the marker
map mirrored (lrfcal.estimate.checks.mirror_check, lrfcal.stages.alternatives.handedness). With the marker map as
it is, a mirror image is another rig, and near a scan plane perpendicular to the motor axis (where it differs from
the estimate by twice alpha in attitude) it can explain the same returns about as well: a second minimum the solver
may or may not have landed in.

:func:`other_minimum` solves the marker-only problem again from the estimate's mirror image (the mount kept) when
the nominal DH cannot rule that image out (it is within the nominal tolerance, lrfcal.estimate.checks), and compares the
two solutions:

- the same rig when every DH parameter of the one (or of its "turned" representative) is within
  :data:`SAME_SIGMA` of the other's sigma;
- otherwise by the likelihood ratio of their whitened residuals over the returns both keep,
  Lambda = (cost_other - cost_estimate) / s^2 (s^2 the estimate's reduced chi-square, at least 1): two distinct
  rigs explain the data equally well when |Lambda| is below :data:`LR_LIMIT`, and the estimate is not the best
  minimum when Lambda is below -LR_LIMIT. Both are refused naming the two rigs.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import CalibrationError
from lrfcal.estimate.checks import CheckConfig, dh_text, judge_minima, nominal_distance
from lrfcal.estimate.information import model_residuals
from lrfcal.estimate.solve import Solver
from lrfcal.model.kinematics import DH, Params, dh_twins
from lrfcal.model.marker import MarkerSensor
from lrfcal.model.motor import Clock, MotorClock
from lrfcal.model.unknowns import dh_difference
from lrfcal.types import Check, MarkerMap, Nominal, Observations, Solution, SurfaceReturns

FloatArray = NDArray[np.float64]

#: DH differences within this many sigma (the estimate's) are one minimum
SAME_SIGMA = 4.0

NAME = "other minimum"


def other_minimum(sol: Solution, matched: Observations, markers: MarkerMap, nominal: Nominal, config: CheckConfig,
                  fit: Solver) -> Check:
    """The marker-only solution ``sol`` of the returns ``matched`` against the minimum its mirror image leads to
    (module docstring), the clock offset held at the estimate's: passed unless a distinct rig explains the data as
    well or better."""
    twin = dh_twins(sol.params.dh)[1][1]  # "mirrored", the marker map as it is
    if nominal_distance(twin, nominal.dh, config)[0] > 1.0:
        return Check(NAME, True, f"not searched: the estimate's mirror image ({dh_text(twin)}) is beyond the "
                                 "nominal tolerance")
    none = Check(NAME, True, "the solve from the estimate's mirror image found no other minimum")
    try:
        alt = fit(matched, markers, Params(sol.params.mount, twin), clock=Clock(None, sol.clock_offset_s))
    except CalibrationError:
        return none
    z = _dh_z(alt.params.dh, sol)
    if not alt.converged or not np.all(np.isfinite(z)):
        return none
    if np.abs(z).max() <= SAME_SIGMA:
        return Check(NAME, True, f"the solve from the estimate's mirror image returned to it (DH within "
                                 f"{np.abs(z).max():.1f} sigma)")
    lr = _cost(alt, matched, markers, fit.sensor, sol) - _cost(sol, matched, markers, fit.sensor, alt)
    lr /= max(1.0, sol.reduced_chi2)
    ok, words = judge_minima(lr)
    if ok:
        return Check(NAME, True, f"another minimum ({dh_text(alt.params.dh)}) explains the data worse ({words})")
    both = f"{dh_text(sol.params.dh)} and {dh_text(alt.params.dh)}"
    return Check(NAME, False, f"two distinct rigs, {both}: {words}; markers spread further along the motor axis tell "
                              "them apart, or a scan plane further from perpendicular to it")


def plane_cost(returns: SurfaceReturns, sol: Solution, motor: MotorClock, sigma_m: float,
               prior: tuple[FloatArray, FloatArray] | None = None) -> float:
    """The targetless cost of a minimum ``sol`` on the fixed plane ``returns``, comparable between minima: the
    returns reprojected in M at its DH, clock offset and intrinsics, each plane fitted afresh (least squares, twice
    without the returns beyond :data:`CUT_SIGMA` of ``sigma_m`` from it), and the truncated squares
    sum_k min(e_k, c)^2 / sigma_m^2 of their distances e_k (c = CUT_SIGMA sigma_m: the returns the robust passes
    leave out count as at the cut), plus the design drawing's prior ((4,) mean and sigma of the DH; the held ones
    equal in every minimum)."""
    from lrfcal.model.kinematics import points_M
    from lrfcal.model.scanner import true_returns
    from lrfcal.model.unknowns import core_vector

    lam = motor.angle(returns.times_s, sol.clock_offset_s) if returns.times_s is not None else returns.lambda_rad
    dh = sol.params.dh
    r, lam_t, mu_t = true_returns(core_vector(dh, sol.intrinsic_values), returns.ranges_m, lam, returns.mu_rad)
    P = points_M(r, lam_t, mu_t, dh)
    c = CUT_SIGMA * sigma_m
    total = 0.0
    for j in np.unique(returns.surface):
        Q = P[returns.surface == j]
        keep = np.ones(len(Q), dtype=bool)
        for _ in range(3):
            m = Q[keep].mean(0)
            n = np.linalg.svd(Q[keep] - m, full_matrices=False)[2][2]
            e = np.abs((Q - m) @ n)
            keep = e <= c
            if keep.sum() < 3:
                break
        total += float(np.sum(np.minimum(e, c) ** 2))
    total /= sigma_m**2
    if prior is not None:
        total += float(np.sum((dh_difference(dh.vector(), prior[0]) / prior[1]) ** 2))
    return total


#: the truncated squares' cut of :func:`plane_cost`, in sigma (the robust passes' rejection)
CUT_SIGMA = 4.0


def _dh_z(dh: DH, sol: Solution) -> FloatArray:
    """(4,) DH differences of ``dh`` (or of its "turned" representative, whichever is nearer) from ``sol``'s, in
    ``sol``'s sigma."""
    def z(cand: DH) -> FloatArray:
        return dh_difference(cand.vector(), sol.params.dh.vector()) / np.asarray(sol.sigma[6:10], dtype=float)

    return min((z(dh), z(dh_twins(dh)[0][1])), key=lambda v: float(np.nanmax(np.abs(v))))


def _cost(sol: Solution, matched: Observations, markers: MarkerMap, sensor: MarkerSensor, other: Solution
          ) -> float:
    """The sum of squared whitened residuals (range and lateral, lrfcal.estimate.information.model_residuals) of ``sol``
    over the returns it and ``other`` both keep, the motor angles at its own clock offset."""
    keep = np.ones(len(matched), dtype=bool)
    for s in (sol, other):
        if s.inlier is not None:
            keep &= s.inlier
    obs = matched if sol.lambda_rad is None else replace(matched, lambda_rad=sol.lambda_rad)
    res, _ = model_residuals(sol.params, obs.subset(keep), markers.positions_W, sensor=sensor)
    return float(res @ res)


__all__ = ["CUT_SIGMA", "SAME_SIGMA", "other_minimum", "plane_cost"]
