"""The scanner's reported range and its intrinsics: what the scanner would report without its systematic errors.

    r_true = r - range_offset - marker_range_bias [marker returns only]

Every observation model compares its predicted range with r_true; the partial derivatives dr_true/dtheta are the
range columns of its Jacobian (:func:`true_range`), so an unknown acting on the range (an offset, a bias of strong
returns, a scale) is written here once.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .unknowns import MBIAS, ROFF

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


__all__ = ["TrueRange", "true_range"]
