"""The range noise's correlation along the beams of a scan, as an AR(1) process: the noise of two returns of the
same scan k beams apart correlates as rho^|k|, returns of different scans are independent (measured rho = 0.70 and
0.56 between neighbouring beams on two real URG-04LX recordings, docs/real-data.md; lrfsim draws it so,
``sensor.noise_correlation``).

A least-squares estimate that weights its residuals as independent (every stage of the calibration) is then still
unbiased, but its covariance is the sandwich H^-1 (J^T C J) H^-1, C the residuals' correlation, instead of H^-1
(H = J^T J, whitened rows). With the range noise entering one row per return (the "sphere" marker model's range
row, a surface return's ray-plane row) with unit whitened variance, J^T C J = H + Delta,

    Delta = sum over pairs i != j of returns in the same scan  rho^|beam_i - beam_j| u_i u_j^T,

u_i (p,) the Jacobian row of return i's range residual: :func:`correlated_range_excess` computes Delta.

rho is a property of the scanner, measured on its own recording: :func:`neighbour_correlation`, the correlation of
the whitened range residuals of neighbouring beams (lrfcal.estimate.scatter measures it on the marker returns;
`lrfsim plan` takes the scenario's ``sensor.noise_correlation``).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: pairs whose correlation rho^|k| is below this are left out (rho = 0.7: beams up to 38 apart)
MIN_PAIR_CORRELATION = 1e-6


def _pairs_by_lag(scan: IntArray, beam: IntArray, rho: float, min_correlation: float
                  ) -> Iterator[tuple[IntArray, IntArray, FloatArray]]:
    """:func:`correlated_pairs` in parts, one per lag in the returns' (scan, beam) order (each part's arrays
    (L_lag,))."""
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"range noise correlation must be in [0, 1), got {rho}")
    scan, beam = np.asarray(scan, dtype=np.int64), np.asarray(beam, dtype=np.int64)
    if rho == 0.0 or scan.size < 2:
        return
    order = np.lexsort((beam, scan))
    s, b = scan[order], beam[order]
    max_gap = np.log(min_correlation) / np.log(rho)  # beams further apart correlate less than min_correlation
    for lag in range(1, scan.size):  # sorted by beam within a scan: the gap grows with the lag
        gap = b[lag:] - b[:-lag]
        near = (s[lag:] == s[:-lag]) & (gap <= max_gap)
        if not np.any(near):
            return
        k = np.flatnonzero(near)
        yield order[k], order[k + lag], rho ** gap[k].astype(float)


def correlated_pairs(scan: IntArray, beam: IntArray, rho: float, min_correlation: float = MIN_PAIR_CORRELATION
                     ) -> tuple[IntArray, IntArray, FloatArray]:
    """The pairs of returns (scan, beam: (K,) each) whose range noise correlates: indices i, j (L,) with i != j in
    the same scan, each unordered pair once, and their correlation rho^|beam_i - beam_j| (L,), those at least
    ``min_correlation``. Returns on the same beam of a scan (echoes) correlate fully (rho^0). Empty for rho = 0.

    Raises:
        ValueError: rho outside [0, 1).
    """
    parts = list(_pairs_by_lag(scan, beam, rho, min_correlation))
    if not parts:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    i, j, w = zip(*parts, strict=True)
    return np.concatenate(i), np.concatenate(j), np.concatenate(w)


def correlated_range_excess(u: FloatArray, scan: IntArray, beam: IntArray, rho: float) -> FloatArray:
    """Delta (p, p) (module docstring): what the range noise's correlation along the scan adds to J^T J in the
    sandwich's middle, from the Jacobian rows u (K, p) of the returns' whitened range residuals, their scans and
    beams (K,) each, and rho, the correlation of neighbouring beams (accumulated lag by lag: no (pairs, p) arrays).

    Raises:
        ValueError: rho outside [0, 1).
    """
    U = np.asarray(u, dtype=float)
    cross = np.zeros((U.shape[1], U.shape[1]))
    for i, j, w in _pairs_by_lag(scan, beam, rho, MIN_PAIR_CORRELATION):
        cross += (U[i] * w[:, None]).T @ U[j]
    return cross + cross.T


#: the largest correlation of neighbouring beams taken from a recording (an AR(1) process needs rho < 1)
MAX_RHO = 0.95
#: a correlation measured from n neighbouring pairs counts where it is at least this many of its standard errors
#: (1 / sqrt(n)) from 0; below, it is taken as 0. Taken as measured from 24 pairs at rho 0, it came out 0.16 and 0.38
#: and refused a points layout (seed 2014) for observability: the sigma only ever widens with it
RHO_Z = 2.0


def shown(rho: float, pairs: int) -> bool:
    """Whether a correlation ``rho`` measured from ``pairs`` neighbouring pairs (:func:`neighbour_correlation`) is
    shown by them (:data:`RHO_Z`): the one rule the covariance (lrfcal.estimate.scatter) and the calibration file
    follow."""
    return pairs > 0 and rho * math.sqrt(pairs) >= RHO_Z


def neighbour_correlation(residuals: FloatArray, scan: IntArray, beam: IntArray) -> tuple[float, int]:
    """The correlation of the range residuals (K,) of returns on neighbouring beams of one scan (scan, beam (K,)
    each), clipped to [0, MAX_RHO], and the number of neighbouring pairs it is taken from (0: rho 0). The residuals of
    a fit are slightly less correlated than the noise (the fit takes up a little of what neighbours share); on
    lrfsim recordings drawn with rho 0.7 it is 0.69-0.70 from the surface returns' 34 000 pairs (points layout
    2010) and 0.56-0.79 from a V's 60 pairs of marker returns."""
    r = np.asarray(residuals, dtype=float)
    order = np.lexsort((beam, scan))
    s, b, x = np.asarray(scan)[order], np.asarray(beam)[order], r[order]
    near = (s[1:] == s[:-1]) & (b[1:] - b[:-1] == 1)
    if not np.any(near):
        return 0.0, 0
    x1, x2 = x[1:][near], x[:-1][near]
    denom = math.sqrt(float(x1 @ x1) * float(x2 @ x2))
    rho = float(x1 @ x2) / denom if denom > 0 else 0.0
    return min(max(rho, 0.0), MAX_RHO), int(near.sum())


__all__ = ["MAX_RHO", "MIN_PAIR_CORRELATION", "RHO_Z", "correlated_pairs", "correlated_range_excess",
           "neighbour_correlation", "shown"]
