"""A range error along the scan that belongs to the beam: the scanner's own pattern, the same in every scan.

A triangulating or phase-measuring scanner's range carries a small error that depends on the beam's place in the
scan and repeats from scan to scan (the real URG-04LX box of docs/real-data.md: 1.2 mm every 61 beams, the pattern of
one quarter of the recording correlating 0.93-0.95 with another's). No DH parameter explains it, and a targetless
calibration on planes takes it up in alpha, beta and b (the URG replicas: docs/real-data.md). Modelled here as one
range offset per bin of :data:`WIDTH_BEAMS` beams, added to every range of the bin's beams:

    reported range = rep(r_true) + p[bin],   p = Z z,

where Z (n_bins, q) spans the bin patterns without their polynomial part of degree :data:`DEGREE` over the bins: a
slowly varying range error along the scan is what the DH, the range offset and the planes take up already (it
cannot be told from them), so it is held, and z (q,) are the unknowns. The pattern is a nuisance of the cost like
the planes' normals and offsets: estimated with the DH, never reported as an intrinsic, its uncertainty carried
into the DH's covariance.

It enters linearly, so it is eliminated exactly (variable projection, Golub and Pereyra 1973): the residuals the
cost sees are those with the best pattern for them taken out (:func:`projected`), and the normal equations carry the
pattern's columns beside the core unknowns (lrfcal.estimate.normal_equations), whose Schur complement is the
information of the DH with the pattern unknown. With the whitened residual (r - rep) / sigma_r, a bin's column is
-1 / sigma_r on the rows of its beams: :class:`PatternRows` holds each row's bin and that value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: beams per bin: a pattern of period 61 beams (the URG-04LX's) has 10 bins a period
WIDTH_BEAMS = 6
#: the pattern's polynomial part over the bins (degree) held: what the DH, the range offset and the planes take up
DEGREE = 2


def beam_bins(beam: IntArray, width: int = WIDTH_BEAMS) -> IntArray:
    """Each return's bin (K,) from its beam's index in the scan (K,)."""
    return np.asarray(beam, dtype=np.int64) // width


def basis(n_rows_per_bin: FloatArray, degree: int = DEGREE) -> FloatArray:
    """Z (n_bins, q): orthonormal bin patterns orthogonal to the polynomials of ``degree`` over the bins that have
    rows (``n_rows_per_bin`` (n_bins,) > 0); 0 on the bins without rows. q = bins with rows - degree - 1 (0 when
    there are no more bins than that)."""
    seen = np.flatnonzero(n_rows_per_bin > 0)
    Z = np.zeros((n_rows_per_bin.size, max(seen.size - degree - 1, 0)))
    if Z.shape[1] == 0:
        return Z
    x = seen.astype(float)
    V = np.vander((x - x.mean()) / max(float(x.std()), 1.0), degree + 1)
    Z[seen] = np.linalg.qr(V, mode="complete")[0][:, degree + 1:]
    return Z


@dataclass(frozen=True)
class PatternRows:
    """The pattern's columns of K plane rows: row k's column is ``value`` times Z[bins[k]] (q,)."""

    bins: IntArray  # (K,)
    value: float  # d whitened residual / d its bin's range offset: -1 / sigma_r
    Z: FloatArray  # (n_bins, q)

    @property
    def q(self) -> int:
        """The pattern's unknowns."""
        return int(self.Z.shape[1])

    def sums(self, weights: FloatArray) -> FloatArray:
        """(q,) sum over the rows of weights (K,) times the row's column."""
        return self.value * (np.bincount(self.bins, weights=weights, minlength=self.Z.shape[0]) @ self.Z)

    def gram(self, w: FloatArray | None = None) -> FloatArray:
        """(q, q) the pattern columns' own information, each row weighted by w (K,) (None: 1)."""
        n = np.bincount(self.bins, weights=w, minlength=self.Z.shape[0])
        return self.value ** 2 * (self.Z.T * n) @ self.Z


def pattern_rows(bins: IntArray, sigma_r: float, degree: int = DEGREE) -> PatternRows:
    """The pattern's columns for plane rows in ``bins`` (K,) (:func:`beam_bins`), whitened by ``sigma_r`` [m]."""
    n_bins = int(bins.max()) + 1 if bins.size else 0
    return PatternRows(bins, -1.0 / sigma_r, basis(np.bincount(bins, minlength=n_bins).astype(float), degree))


def estimated_m(res: FloatArray, rows: PatternRows) -> FloatArray:
    """The pattern (n_bins,) [m] the whitened residuals (K,) hold (its polynomial part 0): the least-squares z of
    X z = res, X the rows' pattern columns, as p = -Z z (res - value Z z = (r - rep - p) / sigma_r)."""
    if rows.q == 0:
        return np.zeros(rows.Z.shape[0])
    return -(rows.Z @ np.linalg.solve(rows.gram(), rows.sums(res)))


def projected(res: FloatArray, rows: PatternRows) -> FloatArray:
    """The whitened residuals (K,) with the best pattern for them taken out, res - X (X^T X)^-1 X^T res (the
    variable projection's residual): the reported ranges less :func:`estimated_m`, whitened."""
    if rows.q == 0:
        return res
    return res + rows.value * estimated_m(res, rows)[rows.bins]


__all__ = ["DEGREE", "WIDTH_BEAMS", "PatternRows", "basis", "beam_bins", "estimated_m", "pattern_rows", "projected"]
