"""Each plane's pull on a solution: where the estimate would go without one plane's returns, and how far it may go
by the noise alone (Cook's distance for a cluster, Cook 1977; the leave-one-cluster-out shift of a least-squares fit).

At the solution the gradients of the planes' marginal costs cancel: sum_j g_j = 0 (the dense rows, the design
drawing's prior, have none there but their own). Without plane j, one Gauss-Newton step from the solution moves the
core unknowns by

    d_j = (S - S_j)^-1 g_j,

S the core unknowns' marginal information (every plane's nuisances eliminated: lrfcal.estimate.normal_equations),
S_j = A_j - B_j D_j^-1 B_j^T and g_j = J_cj^T r_j - B_j D_j^-1 (J_nj^T r_j + the plane prior's term) plane j's own
parts of it. Where every plane is a plane the model explains, d_j is noise, with the covariance of the difference
of two nested least-squares estimates, (S - S_j)^-1 - S^-1 (unit noise). A plane that is not one surface the DH
model explains (two surfaces taken as one, a curved or moving one, a range error along the scan that one plane's
returns share) pulls the estimate by more than that: the check "planes agree" (lrfcal.estimate.checks) judges the
pulls against the stated sigma, where the other planes alone (without the design drawing's prior) determine the DH.

The scanner's range pattern along the scan (lrfcal.model.range_pattern), where the cost has one, is held at its
estimate from every plane: a pull asks whether a plane agrees with the others on the DH parameters given the
scanner, not whether the others alone can tell the DH from a range error per bin of beams. Re-estimated without the
plane, the pattern's bins rest on the few small planes (furniture) their beams see, and what those few returns share
beyond the noise reaches the DH: on the furnished room replica (scenarios/urg_room_90.yaml, seed 1006, the wiggle
left out of the data so that the true pattern is zero) the wall across the motor axis then pulls alpha by 5.7 sigma,
chi-square 29.7 on 4 (with the room's furniture left out no plane beyond chi-square 5.3); with the pattern held, by
0.1 sigma (docs/real-data.md).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from lrfcal.estimate.normal_equations import Normal, plane_segments, schur
from lrfcal.model.observations import Blocks
from lrfcal.types import PlanePulls

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def plane_pulls(b: Blocks, N: Normal, core: IntArray, V: FloatArray, scale: float, names: tuple[str, ...]
                ) -> PlanePulls | None:
    """The pull of each plane of ``b`` (module docstring) over the core columns ``core`` (c,) named ``names``: N the
    normal equations of ``b`` over them (its planes' B_j, D_j and nuisance gradients, their priors included), V
    (c, c) the core block of the inverse information (unit noise) at the solution whose blocks ``b`` are (where N
    has a range pattern, the one with the pattern held is used instead: module docstring); the difference
    covariances times ``scale`` (the statistical covariance's noise variance, lrfcal.estimate.covariance). None
    without planes."""
    P = b.n_planes
    if P == 0 or b.Jc_plane is None:
        return None
    c = core.size
    if N.pattern is not None:  # the range pattern held at its estimate from every plane (module docstring)
        N = N.given_pattern
        S = schur(N)[0]
        V = np.asarray(np.linalg.inv(S), dtype=np.float64)
    else:
        S = np.asarray(np.linalg.inv(V), dtype=np.float64)
    shift, difference, others = np.zeros((P, c)), np.zeros((P, c, c)), np.full((P, c), np.inf)
    dense = b.J_dense[:, core] if b.J_dense is not None else np.zeros((0, c))
    planes_only = S - dense.T @ dense  # without the dense rows (the design drawing's prior on the DH)
    returns = np.bincount(b.plane, minlength=P)
    Jc, r = b.Jc_plane[:, core], b.r_plane
    order, bounds = b.segments if b.segments is not None else plane_segments(b.plane, P)
    for j in range(P):
        rows = order[bounds[j]:bounds[j + 1]]
        if rows.size == 0:
            continue
        BDi = N.B[:, 3 * j:3 * j + 3] @ np.linalg.pinv(N.D[j], rcond=1e-12)
        S_j = Jc[rows].T @ Jc[rows] - BDi @ N.B[:, 3 * j:3 * j + 3].T
        S_j = 0.5 * (S_j + S_j.T)
        g_j = Jc[rows].T @ r[rows] - BDi @ N.g_n[3 * j:3 * j + 3]
        try:
            V_without = np.linalg.inv(S - S_j)
        except np.linalg.LinAlgError:  # the others alone determine nothing there: no pull to judge
            shift[j], difference[j] = np.nan, np.nan
            continue
        shift[j] = V_without @ g_j
        difference[j] = scale * (V_without - V)
        alone = planes_only - S_j
        if np.linalg.matrix_rank(alone) == c:
            others[j] = np.sqrt(scale * np.maximum(np.diag(np.linalg.inv(alone)), 0.0))
    return PlanePulls(names=names, returns=returns, shift=shift, difference=difference, others=others)


__all__ = ["plane_pulls"]
