"""The noise a solution's residuals show, where the model's stated sigma is a bound or leaves a correlation out: the
statistical covariance of lrfcal.estimate.covariance.uncertainty (and of `lrfsim plan`, lrfcal.estimate.information).

* **The lateral means' scatter.** A marker's lateral residual keeps one mean per crossing (across the scan plane)
  and one per scan line (along it) (lrfcal.model.coverage). The model's sigma of such a mean, R_m sqrt(1 + k^2) / 2
  over the root of the lines or beams averaged, is what it would be if each line fell anywhere on the disc. But the
  lines of a crossing step across the disc at a regular spacing, and so do the beams of a line: their mean misses the
  centre by a fraction of one spacing. On a V on both walls (layout seed 2002) the crossings' means scattered with
  0.1-0.4 of the stated variance and the lines' with 0.1, and the stated sigma of a and alpha was 1.8x and 1.6x
  their errors' spread (docs/study.md). Each kind of mean is therefore given the variance its own residuals show
  (:func:`lateral_scatter`: their sum of squares over their redundancy less 2), where it has at least
  MIN_REDUNDANT redundant means; kinds with fewer share the scatter of both where together they have as many (a V
  of 6 markers, 12 crossings: RMS of error / sigma 0.54-0.89 at the bound, 0.70-0.98 so; docs/study.md); else the
  model's sigma stands.
* **The range noise's correlation along the scan** (lrfcal.model.noise): measured from the residuals of neighbouring
  marker returns (:func:`range_rows`, lrfcal.model.noise.neighbour_correlation), its sandwich term over every range
  row (the surface returns' too) enters the covariance as `lrfsim plan` adds it from the scenario's rho. The
  per-crossing sandwich (lrfcal.estimate.covariance) sees the same correlation, but from the few crossings that
  determine b it is a noisy estimate, too narrow on average (b's sigma 1.46x too narrow on scattered points at rho
  0.7, layout 2010: docs/study.md). It counts where the marker returns show it (lrfcal.model.noise.shown). Only the
  marker returns measure rho: a sphere's residual is the scanner's noise, a wall's also holds the wall's unevenness and
  the scanner's range error along the scan, correlated over many beams, which the per-scan sandwich (hundreds of
  scans) takes as it is. Measured on the surface returns of the real recordings of docs/real-data.md, rho moved
  room_240's verdict (its halves' chi2 376 -> 147, one half refused for another reason). A recording without
  markers (the targetless calibration) keeps the per-scan sandwich alone.

The estimate itself weights the rows as the model states (the lateral means at their bound): what changes is the
covariance, H^-1 (sum over kinds of s2_kind H_kind) H^-1, the sandwich of an estimate whose weights are not the
inverse variances.

Array shapes: nc core unknowns estimated; R range rows.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from lrfcal.estimate.problem import Problem
from lrfcal.model.marker import MarkerModel
from lrfcal.model.noise import correlated_range_excess, neighbour_correlation, shown
from lrfcal.model.observations import Blocks
from lrfcal.model.plane import PlaneSet

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: a kind of lateral mean gets the variance its residuals show only with at least this many redundant means (its
#: count less the unknowns it determines), alone or pooled with the other kind; with fewer, the estimate of a
#: variance is too loose to narrow a sigma by
MIN_REDUNDANT = 10


class Scatter(NamedTuple):
    """One kind of residual whose variance is measured from its own residuals."""

    s2: float  #: its variance in units of the model's
    H: FloatArray  #: (nc, nc) its information J^T J over the core unknowns
    ss: float  #: its sum of squared whitened residuals
    n_means: float  #: its independent residuals (the means)
    share: float  #: the unknowns it determines, tr(V H)


def lateral_scatter(pb: Problem, b: Blocks, core: NDArray[np.intp], V: FloatArray) -> tuple[Scatter, ...]:
    """The crossings' means across the scan plane and along it (lrfcal.model.marker.MarkerSet.lateral_means) of the
    marker rows among ``b``'s, each kind with the variance the residuals show (:func:`measured`; ``V`` (nc, nc): the
    core block of (J^T J)^-1 over ``core``); a kind they cannot measure is left out (the model's sigma stands)."""
    ms = pb.markers
    if ms is None or b.J_dense is None:
        return ()
    kinds = []
    for rows, J, count in ms.lateral_means(pb.markers_in(b.r_dense), pb.markers_in(b.J_dense)[:, :, core]):
        H = J.T @ J
        kinds.append(Scatter(math.nan, H, float(rows @ rows), count, float(np.trace(V @ H))))
    return measured(kinds)


def measured(kinds: Sequence[Scatter]) -> tuple[Scatter, ...]:
    """The kinds (their ``s2`` not yet set) whose variance their residuals measure, with it: their sum of squares
    over their redundancy nu (count less tr(V H)) less 2, where nu >= MIN_REDUNDANT. Kinds with fewer redundant
    means share the scatter of all of them where their pool has MIN_REDUNDANT (both kinds are means of one marker's
    coverage, lines or beams at a regular spacing: on a V of 6 markers, 12 crossings, the two kinds measured 0.40 and
    0.25 of the bound from 6.6 and 9.5 redundant means), a kind never below its own (where its nu > 2): the pool
    must not lower the kind that scatters more."""
    # over nu - 2, not nu: a variance measured from nu means makes err / sigma a Student t, whose mean square is
    # nu / (nu - 2); so stated, the sigma holds its own uncertainty (1.25x the variance at nu = 10)
    nu = [k.n_means - k.share for k in kinds]
    out = [k._replace(s2=k.ss / (n - 2.0)) for k, n in zip(kinds, nu, strict=True) if n >= MIN_REDUNDANT]
    few = [(k, n) for k, n in zip(kinds, nu, strict=True) if n < MIN_REDUNDANT]
    pooled_nu = sum(n for _, n in few)
    if len(few) > 1 and pooled_nu >= MIN_REDUNDANT:
        pooled = sum(k.ss for k, _ in few) / (pooled_nu - 2.0)
        out += [k._replace(s2=max(pooled, k.ss / (n - 2.0) if n > 2.0 else 0.0)) for k, n in few]
    return tuple(out)


def range_rows(pb: Problem, b: Blocks, core: NDArray[np.intp], A: FloatArray | None = None,
               nu_rows: IntArray | None = None) -> tuple[FloatArray, FloatArray, IntArray, IntArray, int]:
    """The rows the range noise enters once per return: each marker return's range row (the sphere model's) and each
    surface return's ray-plane row of ``b``: their whitened residuals (R,), their effect on the core estimate
    u_i = J_i A (R, nc) (``A`` (n, nc): (J^T J)^-1's columns of the core unknowns, its first nc rows the core's;
    ``nu_rows`` (3P,): the row of A of each plane nuisance; without A, u is (R, 0)), their scans and beams (R,), and
    how many of them, first, are marker returns. Rows whose beams are not known, and plane rows with the range
    pattern taken out of them (lrfcal.model.range_pattern), are left out."""
    k = core.size
    res, U, scan, beam = [], [], [], []
    n_markers = 0
    ms = pb.markers
    if (ms is not None and ms.model == MarkerModel.SPHERE and ms.scan is not None and ms.beam is not None
            and b.J_dense is not None and ms.r.size):
        res.append(pb.markers_in(b.r_dense)[:, 0])
        U.append(np.zeros((ms.r.size, 0)) if A is None else pb.markers_in(b.J_dense)[:, 0][:, core] @ A[:k])
        scan.append(ms.scan)
        beam.append(ms.beam)
        n_markers = ms.r.size
    planes = [s for s in pb.sets if isinstance(s, PlaneSet)]
    if (planes and b.pattern is None and b.Jc_plane is not None and b.Jn_plane is not None
            and all(s.scan is not None and s.beam is not None for s in planes)
            and sum(s.size for s in planes) == b.r_plane.size and b.r_plane.size):
        if A is None or nu_rows is None:
            u = np.zeros((b.r_plane.size, 0))
        else:
            u = b.Jc_plane[:, core] @ A[:k]
            for i in range(3):  # the plane nuisances' columns: 3 per plane
                u += b.Jn_plane[:, i:i + 1] * A[nu_rows[3 * b.plane + i]]
        res.append(b.r_plane)
        U.append(u)
        scan.extend(s.scan for s in planes if s.scan is not None)
        beam.extend(s.beam for s in planes if s.beam is not None)
    if not res:
        return np.zeros(0), np.zeros((0, 0 if A is None else k)), np.zeros(0, np.int64), np.zeros(0, np.int64), 0
    return (np.concatenate(res), np.vstack(U), np.concatenate(scan).astype(np.int64),
            np.concatenate(beam).astype(np.int64), n_markers)


def correlation_excess(u: FloatArray, scan: IntArray, beam: IntArray, rho: float) -> FloatArray:
    """The covariance (nc, nc) that range noise correlated along the scan (neighbouring beams ``rho``) adds to an
    estimate weighting its returns as independent, from :func:`range_rows`' effects ``u``, scans and beams
    (lrfcal.model.noise.correlated_range_excess), symmetric."""
    if rho <= 0.0 or not u.size:
        return np.zeros((u.shape[1], u.shape[1]))
    extra = correlated_range_excess(u, scan, beam, rho)
    return 0.5 * (extra + extra.T)


class Noise(NamedTuple):
    """What a solution's residuals say about its noise (:func:`statistical`)."""

    covariance: FloatArray  #: (n, n) the statistical covariance of every unknown (column-unscaled)
    s2: float  #: the reduced chi-square of the rows at the stated noise (the lateral means measured apart), >= 1
    correlation: tuple[float, int]  #: the range noise's rho along the scan and the neighbouring pairs it is from


def statistical(pb: Problem, b: Blocks, core: NDArray[np.intp], JtJ_inv: FloatArray, nu_rows: IntArray,
                n_rows: float, n_unknowns: int) -> Noise:
    """The statistical covariance of a solution with ``JtJ_inv`` (n, n) (its first nc rows and columns the core
    unknowns ``core``; ``nu_rows`` (3P,): the row of each plane nuisance): the rows at the stated noise scaled by
    their reduced chi-square, never below 1 (the stated noise is the floor: a residual's sigma is the scanner's,
    not less); each kind of lateral mean at the variance its residuals show (:func:`lateral_scatter`); plus the
    range noise's correlation along the scan, measured from the residuals of neighbouring marker returns
    (:func:`range_rows`; module docstring). ``n_rows``: the independent residuals of every set; ``n_unknowns``:
    the unknowns estimated (the range pattern's too)."""
    k = core.size
    V = JtJ_inv[:k, :k]
    res = b.residuals()
    kinds = lateral_scatter(pb, b, core, V)
    ss = float(res @ res) - sum(s.ss for s in kinds)
    redundant = n_rows - sum(s.n_means for s in kinds) - (n_unknowns - sum(s.share for s in kinds))
    s2 = max(ss / max(redundant, 1.0), 1.0)
    cov = s2 * JtJ_inv
    if kinds:
        cov[:k, :k] += V @ sum((s.s2 - s2) * s.H for s in kinds) @ V
    r, _, scan, beam, n_markers = range_rows(pb, b, core)
    rho, pairs = neighbour_correlation(r[:n_markers], scan[:n_markers], beam[:n_markers])
    if shown(rho, pairs):  # the rows' effects on the estimate only where they count
        _, u, scan, beam, _ = range_rows(pb, b, core, JtJ_inv[:, :k], nu_rows)
        cov[:k, :k] += s2 * correlation_excess(u, scan, beam, rho)
    return Noise(cov, s2, (rho, pairs))


__all__ = ["MIN_REDUNDANT", "Noise", "Scatter", "correlation_excess", "lateral_scatter", "measured",
           "range_rows", "statistical"]
