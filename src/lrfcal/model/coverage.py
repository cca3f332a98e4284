"""How a sweep's scan lines cover a marker: its returns' scan lines and crossings, where the sweep turns on it, and
what the lateral residual keeps of its returns (lrfcal.model.marker).

A scan line crosses a sphere of radius R in a chord: its beams hit it at evenly spaced bearings, and the chord lies
at the distance h of the scan plane from the centre. A crossing is a marker's successive lines as the sweep passes
it: their h move across the disc at the sweep's speed. Each return's lateral offset e (the centre's offset from its
ray) therefore has two parts of different nature:

* across the scan plane: h, one value per line, the same for all its beams; over a crossing the lines spread from
  one rim to the other;
* along the scan line (in the plane, across the ray): one value per beam, spread along the chord.

The centre is where the lines and beams balance: the mean of each part. Their spread is not noise about the centre:
it is the disc's width, covered as the beams and the sweep move. A cost that takes each return's offset as an
independent draw about the centre (the uniform filled disc) is smallest where the beams' coverage is narrowest, so
it pulls every unknown that stretches the coverage: the motor's angle scale (the lines of a crossing sweep a
motor angle range proportional to it), and the DH parameters that set a marker's distance from the motor axis. On a
board the motor axis points at (lrfsim.testing.boards, layout seed 2008), noise-free returns at the truth stepped
the motor-angle scale's score test to 0.990 (6 sigma from 1) and took alpha 0.018 deg and b 0.21 mm off; with the
means alone, 0.9995 and 0.003 deg, 0.003 mm (docs/trust.md).

:func:`centred` keeps the means: the across part as one residual per crossing (the mean of its returns' h, weighted
as its lines: sqrt(L / K) on each of its K returns, L lines), the in-plane part as one residual per line (the mean
of its beams' offsets, 1 / sqrt(K_line) on each). Both are linear in the returns' rows, so the Jacobian is the same
means of the rows: the directions (the scan plane's normal, the in-plane direction across each ray) are data, chosen
at each pass's estimate like lrfcal.model.marker.MarkerSet.lateral (MarkerSet.axes).

Array shapes: K returns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: returns of one marker closer in time than this belong to one scan line [s] (a line crosses a marker in a few
#: beams, 17 us apart on the UTM-30LX; scans are 25 ms apart)
LINE_GAP_S = 0.005
#: lines of one marker further apart in time than this belong to different crossings of the sweep [s]
CROSSING_GAP_S = 0.5
#: how far beyond its first and last line a crossing's lines must reach, in marker radii, to count as turning
TURN_EXCURSION = 0.25


def _runs(marker: IntArray, times: FloatArray, gap_s: float) -> IntArray:
    """(K,) each return's run: its marker's returns in time order, a new run where two are more than ``gap_s``
    apart."""
    order = np.lexsort((times, marker))
    m, t = marker[order], times[order]
    new = np.r_[True, (m[1:] != m[:-1]) | (np.diff(t) > gap_s)]
    out = np.empty(marker.size, dtype=np.int64)
    out[order] = np.cumsum(new) - 1
    return out


def crossing_ids(marker: IntArray, times: FloatArray) -> IntArray:
    """(K,) the crossing of each return: its marker's successive scan lines, a new crossing where the lines of one
    marker are more than CROSSING_GAP_S apart."""
    return _runs(marker, times, CROSSING_GAP_S)


def _line_ids(marker: IntArray, times: FloatArray, scan: IntArray | None) -> IntArray:
    """(K,) the scan line of each return: its marker's returns in one scan (``scan`` (K,), each return's scan
    index), or without the scans, its marker's returns closer than LINE_GAP_S in time."""
    if scan is not None:
        return np.unique(np.stack([marker, scan], 1), axis=0, return_inverse=True)[1].reshape(-1).astype(np.int64)
    return _runs(marker, times, LINE_GAP_S)


@dataclass(frozen=True)
class Coverage:
    """The scan lines and crossings of K marker returns (data: from their markers, scans and times alone)."""

    line: IntArray  #: (K,) each return's scan line
    crossing: IntArray  #: (K,) each return's crossing
    per_line: FloatArray  #: (K,) the returns of its line
    per_crossing: FloatArray  #: (K,) the returns of its crossing
    lines_in_crossing: FloatArray  #: (K,) the lines of its crossing

    @classmethod
    def of(cls, marker: IntArray, times: FloatArray, scan: IntArray | None = None) -> Coverage:
        """The coverage of returns on ``marker`` (K,) at ``times`` (K,) [s] in the scans ``scan`` (K,; None: lines
        told apart by time)."""
        line, crossing = _line_ids(marker, times, scan), crossing_ids(marker, times)
        n_l, n_c = int(line.max(initial=-1)) + 1, int(crossing.max(initial=-1)) + 1
        first = np.zeros(line.size, dtype=bool)
        first[np.unique(line, return_index=True)[1]] = True
        return cls(line, crossing, np.bincount(line, minlength=n_l)[line].astype(float),
                   np.bincount(crossing, minlength=n_c)[crossing].astype(float),
                   np.bincount(crossing[first], minlength=n_c)[crossing].astype(float))

    def lateral_dof(self, across: NDArray[np.bool_]) -> FloatArray:
        """(K,) each return's share of the independent lateral residuals :func:`centred` keeps: 1 / K_line of its
        line's in-plane mean, plus 1 / K_crossing of its crossing's across mean where ``across`` (K,) keeps it."""
        return 1.0 / self.per_line + np.where(across, 1.0 / self.per_crossing, 0.0)


def _mean_over(x: FloatArray, group: IntArray) -> FloatArray:
    """``x`` (K, ...) replaced by the mean over each return's ``group`` (K,)."""
    n = int(group.max(initial=-1)) + 1
    flat = x.reshape(x.shape[0], -1)
    counts = np.maximum(np.bincount(group, minlength=n), 1).astype(float)
    means = np.stack([np.bincount(group, flat[:, j], n) for j in range(flat.shape[1])], 1) / counts[:, None]
    return means[group].reshape(x.shape)


def centred(rows: FloatArray, normal: FloatArray, along: FloatArray, cov: Coverage) -> FloatArray:
    """The lateral rows (K, 3) of whitened residuals, or (K, 3, p) of their Jacobian, with their part along
    ``normal`` (K, 3, the scan plane's unit normal) replaced by its crossing's mean times sqrt(L / K_crossing), and
    their part along ``along`` (K, 3, the unit direction in the scan plane across the ray) by its line's mean times
    1 / sqrt(K_line) (module docstring); the part along the ray stays each return's own. Linear in ``rows``: the
    Jacobian's rows are the residual's derivative where the directions are data (lrfcal.model.marker.MarkerSet.axes,
    chosen at each pass's estimate)."""
    f_c = np.sqrt(cov.lines_in_crossing / cov.per_crossing)
    f_l = 1.0 / np.sqrt(cov.per_line)
    if rows.ndim == 2:
        a, b = (rows * normal).sum(1), (rows * along).sum(1)
        a_new, b_new = _mean_over(a, cov.crossing) * f_c, _mean_over(b, cov.line) * f_l
        return rows + (a_new - a)[:, None] * normal + (b_new - b)[:, None] * along
    a, b = np.einsum("ki,kij->kj", normal, rows), np.einsum("ki,kij->kj", along, rows)
    a_new, b_new = _mean_over(a, cov.crossing) * f_c[:, None], _mean_over(b, cov.line) * f_l[:, None]
    return rows + normal[:, :, None] * (a_new - a)[:, None, :] + along[:, :, None] * (b_new - b)[:, None, :]


def turning(h: FloatArray, marker: IntArray, times: FloatArray, radius: float) -> NDArray[np.bool_]:
    """(K,) whether each return belongs to a crossing in which the scan plane turns back on its marker.

    ``h`` (K,): the centre's distance from the scan plane at each return. The lines of one crossing (successive
    scan lines on one marker) move across it monotonically where the sweep goes through, at the sweep's speed:
    uniformly over the disc. Where the sweep turns on the marker (the end of a nodding sweep, or the edge of the
    band a tilted spinning plane sweeps, where a marker's distance from the plane passes its extremum), the lines
    crowd about the turning point and their mean is off the centre towards it: every such marker pulls the scan
    plane's tilt the same way. A crossing turns when its lines reach TURN_EXCURSION radii beyond both its first and
    its last line on one side."""
    out = np.zeros(h.size, dtype=bool)
    order = np.lexsort((times, marker))
    m, t, hh = marker[order], times[order], h[order]
    new_line = np.r_[True, (m[1:] != m[:-1]) | (np.diff(t) > LINE_GAP_S)]
    line = np.cumsum(new_line) - 1
    n_lines = int(line[-1]) + 1 if line.size else 0
    h_line = np.bincount(line, hh, n_lines) / np.bincount(line, minlength=n_lines)
    t_line = np.bincount(line, t, n_lines) / np.bincount(line, minlength=n_lines)
    m_line = m[new_line]
    new_crossing = np.r_[True, (m_line[1:] != m_line[:-1]) | (np.diff(t_line) > CROSSING_GAP_S)]
    crossing = np.cumsum(new_crossing) - 1
    n_cross = int(crossing[-1]) + 1 if crossing.size else 0
    first = h_line[new_crossing]
    last = h_line[np.r_[new_crossing[1:], True]]
    top = np.full(n_cross, -np.inf)
    bottom = np.full(n_cross, np.inf)
    np.maximum.at(top, crossing, h_line)
    np.minimum.at(bottom, crossing, h_line)
    tol = TURN_EXCURSION * radius
    turns = (top > np.maximum(first, last) + tol) | (bottom < np.minimum(first, last) - tol)
    out[order] = turns[crossing[line]]
    return out


__all__ = ["CROSSING_GAP_S", "LINE_GAP_S", "TURN_EXCURSION", "Coverage", "centred", "crossing_ids",
           "turning"]
