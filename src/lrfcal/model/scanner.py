"""The scanner's intrinsics: the true range of a reported one, and the true bearing of a declared one.

    r_true = r - range_offset - marker_range_bias [marker returns only]
    mu_true = beam_scale mu          (mu = angle_min + i angle_increment as the scan declares it; beta, the DH
                                      angle, absorbs any constant, so a wrongly declared increment is a scale)

Every observation model compares its predicted range with r_true and casts its beam at beta + mu_true; the partial
derivatives are the range and bearing columns of its Jacobian (:func:`true_range`, :func:`true_bearing`), so an
unknown acting on the range or the bearing is written here once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .unknowns import BSCALE, MBIAS, ROFF

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrueRange:
    """The ranges r_true (K,) and their partials: (core index, dr_true/dtheta (K,)) per unknown acting on them."""

    r: FloatArray
    partials: tuple[tuple[int, FloatArray], ...]


def true_range(th: FloatArray, r: FloatArray, on_marker: bool) -> TrueRange:
    """r_true of the reported ranges ``r`` (K,) at the unknowns ``th`` (module docstring); ``on_marker``: the returns
    are from retroreflective markers (their range bias applies)."""
    r = np.asarray(r, dtype=float)
    one = np.full(r.shape, -1.0)
    if on_marker:
        return TrueRange(r - th[ROFF] - th[MBIAS], ((ROFF, one), (MBIAS, one)))
    return TrueRange(r - th[ROFF], ((ROFF, one),))


@dataclass(frozen=True)
class TrueBearing:
    """The bearings mu_true (K,) and their partials: (core index, dmu_true/dtheta (K,)) per unknown acting on them."""

    mu: FloatArray
    partials: tuple[tuple[int, FloatArray], ...]


def true_bearing(th: FloatArray, mu: FloatArray) -> TrueBearing:
    """mu_true of the declared bearings ``mu`` (K,) at the unknowns ``th`` (module docstring)."""
    mu = np.asarray(mu, dtype=float)
    return TrueBearing(th[BSCALE] * mu, ((BSCALE, mu),))


__all__ = ["TrueBearing", "TrueRange", "true_bearing", "true_range"]
