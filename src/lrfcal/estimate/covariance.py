"""The uncertainty of a solution of lrfcal.estimate.solve: its statistical covariance at the noise its residuals show
(lrfcal.estimate.scatter: s^2 (J^T J)^-1 with the lateral means at their own scatter and the range noise's
correlation along the scan), widened where errors shared within a scan or by the returns of one marker make it
optimistic (cluster-robust sandwiches), plus the marker map's own uncertainty carried through the solution
(:func:`uncertainty`); and the score tests of the unknowns the model holds
by default (:func:`held_score`), whose sigma is the one the estimate would have.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from types import MappingProxyType
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from lrfcal.estimate.influence import plane_pulls
from lrfcal.estimate.normal_equations import RANK_TOL, Blocks, assemble, schur, scores_by_cluster, solve_step
from lrfcal.estimate.observability import marginal_information
from lrfcal.estimate.problem import Problem
from lrfcal.estimate.scatter import statistical
from lrfcal.model.unknowns import CORE_NAMES, N_CORE, UNKNOWNS
from lrfcal.types import Spread

FloatArray = NDArray[np.float64]


def inflate_for_correlation(cov: FloatArray, G: FloatArray, JtJ_inv: FloatArray) -> FloatArray:
    """Widen the covariance where errors shared within a scan make it optimistic.

    The cluster-robust (sandwich) covariance (J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1, g_c = sum over the rows of
    scan c of J_i r_i (G (clusters, p), lrfcal.estimate.normal_equations.scores_by_cluster), allows any error
    correlation within
    a scan (the motor angle of a scan comes from the same few quantised encoder readings for all its beams). Each
    parameter's sigma is the larger of the two; the model-based correlations are kept. cov (p, p).
    """
    return widen(cov, JtJ_inv @ (G.T @ G) @ JtJ_inv)


def widen(cov: FloatArray, sandwich: FloatArray) -> FloatArray:
    """``cov`` (p, p) with each parameter's sigma the larger of its own and the ``sandwich``'s (p, p), the
    correlations kept."""
    with np.errstate(over="ignore", divide="ignore", invalid="ignore"):  # a null-variance column stays unscaled
        ratio = np.diag(sandwich) / np.diag(cov)
    scale = np.sqrt(np.maximum(1.0, np.where(np.isfinite(ratio), ratio, 1.0)))
    return cov * np.outer(scale, scale)


#: markers needed for the per-marker sandwich (fewer: it says nothing)
_MIN_MARKER_CLUSTERS = 4
#: a null direction of the information (unit vector, column-scaled) whose components on the core unknowns all stay
#: below this lies in the nuisances alone: no rank loss of the core (:func:`uncertainty`)
NULL_CORE_TOL = 1e-6


def inflate_for_markers(cov: FloatArray, b: Blocks, core: NDArray[np.intp], marker_dense: NDArray[np.int64],
                         scan_plane: NDArray[np.int64], JtJ_inv: FloatArray, live: NDArray[np.bool_] | None = None
                         ) -> FloatArray:
    """Widen ``cov`` (p, p) per parameter to the cluster-robust covariance with every marker's returns one cluster
    (each scan's surface returns one, as before), times G / (G - 1) for G markers: the errors the returns of one
    marker share (an uneven coverage of its disc by the beams, the marker map's error of it) are then counted once
    per marker, not as independent per return. The larger of the two per parameter, the correlations kept. ``live``
    (c + 3P,): the columns the covariance keeps (None: all)."""
    n_markers = np.unique(marker_dense).size
    if n_markers < _MIN_MARKER_CLUSTERS:
        return cov
    ids = marker_dense + (int(scan_plane.max()) + 1 if scan_plane.size else 0)  # apart from the scans' ids
    G = scores_by_cluster(b, core, ids, scan_plane)[1]
    if live is not None:
        G = G[:, live]
    return widen(cov, JtJ_inv @ (G.T @ G) @ JtJ_inv * (n_markers / (n_markers - 1)))


def map_sensitivity(pb: Problem, th: FloatArray, R_ref: FloatArray, b: Blocks, core: NDArray[np.intp],
                    live: NDArray[np.bool_], JtJ_inv: FloatArray, n_markers: int) -> FloatArray:
    """How the estimate moves with the marker map, G (len(core), 3 n_markers): by G dc, G = -(J^T J)^-1 J^T J_c (one
    Gauss-Newton step), through the marker rows (core columns) and the planes' priors (the ``live`` nuisance
    columns of ``JtJ_inv``)."""
    cross = pb.centre_cross(th, R_ref, core, n_markers, b.J_dense)
    prior = pb.prior_cross(n_markers)  # one row per nuisance, in H's order after the core
    if prior is not None:
        cross = np.vstack([cross, prior[live[core.size:]]])
    return -JtJ_inv[:core.size, :cross.shape[0]] @ cross


class Covariance(NamedTuple):
    """The covariance at a solution (:func:`uncertainty`)."""

    covariance: FloatArray  #: (N_CORE, N_CORE) the core's: NaN rows held, inf where the information is singular
    information: FloatArray  #: the marginal information over the free core unknowns
    names: tuple[str, ...]  #: their names
    reduced_chi2: float  #: s^2 of every row at its stated sigma
    rank: str  #: the rank in words
    map_sensitivity: FloatArray | None  #: G (N_CORE, 3n); None without the map's covariance or with rank loss
    #: each cluster's influence and the statistical covariance at the stated noise times the floor of its reduced
    #: chi-square (lrfcal.estimate.checks); empty with rank loss
    spread: Spread
    #: the range noise's rho along the scan the marker returns show and its pairs (scatter.Noise); (0, 0) with rank
    #: loss
    range_correlation: tuple[float, int]
    #: the score tests of held unknowns, name -> (value, sigma) (:func:`held_score`; the engine adds them, lrfcal.
    #: estimate.engine.estimate)
    held_score: Mapping[str, tuple[float, float]] = MappingProxyType({})


def uncertainty(pb: Problem, th: FloatArray, R_ref: FloatArray, free: NDArray[np.bool_],
                 map_cov: FloatArray | None = None, blocks: Blocks | None = None) -> Covariance:
    """The covariance at the solution: the statistical covariance over the free unknowns at the noise the residuals
    show (lrfcal.estimate.scatter.statistical: s^2 (J^T J)^-1, the lateral means at their own scatter, the range
    noise's correlation along the scan), widened for errors shared within a cluster (its sets' clusters,
    Problem.clusters: the cluster of each dense and plane residual row, a marker's crossing
    (lrfcal.model.marker.MarkerSet.clusters) and a scan's surface returns; each prior row is a cluster of its own),
    with its sets' independent residuals (ObservationSet.n_independent), plus the marker map's own uncertainty
    ``map_cov`` (3n, 3n) carried through the solution: G map_cov G^T, G = -(J^T J)^-1 J^T J_c
    (lrfcal.estimate.problem.Problem.centre_cross). Then widened again where the errors shared by all returns of one
    marker (the sets' groups: the marker of each dense row) say more: where the beams cover a marker unevenly (lines
    fanning across it, or the same lines in every pass), the mean of its returns' lateral offsets is not its centre,
    and that error is common to the marker (:func:`inflate_for_markers`). J^T J from the normal equations,
    column-scaled; an eigenvalue below RANK_TOL of the largest is rank loss. Returns :class:`Covariance`.
    ``blocks``: ``pb.blocks(th, R_ref)`` when the caller has them already (they are read, not changed)."""
    b = pb.blocks(th, R_ref) if blocks is None else blocks
    core = np.flatnonzero(free[:N_CORE])
    normal = assemble(b, core)
    H, _ = normal.dense()
    # a plane the robust passes left without a return (and without a prior) carries no information: its nuisances
    # are no unknowns of this covariance (not a rank loss of the core)
    live = np.ones(H.shape[0], dtype=bool)
    live[core.size:] = np.diag(H)[core.size:] > 0
    if not live.all():
        H = H[np.ix_(live, live)]
    res = b.residuals()
    n_par = H.shape[0]
    n_rows = sum(s.n_independent for s in pb.sets)
    cluster_dense, cluster_plane, marker_dense = pb.clusters()
    n_pattern = 0 if normal.pattern is None else normal.pattern.g.size  # the range pattern's unknowns, eliminated
    s2 = float(res @ res / max(n_rows - n_par - n_pattern, 1))
    col = np.sqrt(np.diag(H))
    col[col == 0] = 1.0
    H_s = H / np.outer(col, col)  # column-scaled: the covariance is computed in these units, then scaled back
    eig, vec = np.linalg.eigh(H_s)
    null = eig <= eig[-1] * RANK_TOL  # only numerically null directions count as rank loss
    rank = n_par - int(null.sum())
    # a null direction of the planes' nuisances alone (a plane whose returns one half of a sweep holds on one line:
    # its tilt about that line) leaves the core's covariance what it is (H is positive semi-definite, so H [0; v] = 0
    # and the pseudo-inverse's core block is the inverse of the core's marginal information): only a null direction
    # that moves a core unknown is rank loss
    core_rank_loss = bool(np.any(np.abs(vec[:core.size, null]) > NULL_CORE_TOL))
    core_pos = list(range(core.size))
    core_names = tuple(CORE_NAMES[k] for k in core)
    G: FloatArray | None = None
    info_scale = 1.0 / max(s2, 1.0)  # the information per unit of the (possibly widened) noise
    if core_rank_loss:
        cov = s2 * np.linalg.pinv(H_s, rcond=1e-15) / np.outer(col, col)
        spread = Spread(np.zeros(0, dtype=np.int64), np.zeros((0, N_CORE)), np.full((N_CORE, N_CORE), np.nan))
        info = marginal_information(H * info_scale, core_pos)
        rank_txt = f"rank deficient ({rank}/{n_par})"
    else:
        JtJ_inv = (np.linalg.inv(H_s) if rank == n_par else np.linalg.pinv(H_s, rcond=RANK_TOL, hermitian=True)
                   ) / np.outer(col, col)
        ids, scores = scores_by_cluster(b, core, cluster_dense, cluster_plane, normal.pattern)
        scores = scores if live.all() else scores[:, live]
        # the noise the residuals show (lrfcal.estimate.scatter): the stated noise is the floor of the rows' (a
        # reduced chi-square below 1 said the lateral means' bound was loose, 0.38 on a rig whose lines hold one or
        # two beams, not that the range noise is smaller than the rig file states); the lateral means at their own
        # scatter; the range noise's correlation along the scan
        noise = statistical(pb, b, core, JtJ_inv, core.size + np.cumsum(live[core.size:]) - 1, n_rows,
                            n_par + n_pattern)
        cov = inflate_for_correlation(noise.covariance, scores, JtJ_inv)
        V = JtJ_inv[np.ix_(core_pos, core_pos)]
        spread = Spread(ids, np.zeros((ids.size, N_CORE)), np.full((N_CORE, N_CORE), np.nan),
                        plane_pulls(b, normal, core, V, noise.s2, core_names))
        # the difference of two nested solutions (a part of the data and the whole) is judged at one noise for
        # both: the rows at their stated sigma, scaled by the floor (each solution's own measured scatter of the
        # lateral means would make C_part - C_joint shrink where only the whole has enough crossings to measure it:
        # a tilted rig's means scattered 4.7x their bound, its parts' too few to say, and the parts' agreement was
        # refused at chi2 51); what the data show beyond it enters as each cluster's influence
        spread.statistical[np.ix_(core, core)] = noise.s2 * V
        spread.influence[:, core] = (scores @ JtJ_inv)[:, core_pos]
        if map_cov is not None:
            G_free = map_sensitivity(pb, th, R_ref, b, core, live, JtJ_inv, len(map_cov) // 3)
            cov[np.ix_(core_pos, core_pos)] += G_free @ map_cov @ G_free.T
            G = np.zeros((N_CORE, len(map_cov)))
            G[core] = G_free
        if marker_dense is not None:
            cov = np.asarray(inflate_for_markers(cov, b, core, marker_dense, cluster_plane, JtJ_inv,
                                                 None if live.all() else live), dtype=np.float64)
        info = np.linalg.inv(cov[np.ix_(core_pos, core_pos)])
        rank_txt = f"full rank (condition {np.sqrt(eig[-1] / eig[~null][0]):.2e})" + (
            "" if rank == n_par else f"; {n_par - rank} direction(s) of the planes alone undetermined")
    cov_core = np.full((N_CORE, N_CORE), np.nan)
    cov_core[np.ix_(core, core)] = cov[np.ix_(core_pos, core_pos)]
    correlation = (0.0, 0) if core_rank_loss else noise.correlation
    if core_rank_loss:
        # a covariance from a singular information would be meaningless (and can be 0): none is reported
        cov_core[np.ix_(core, core)] = np.inf
    return Covariance(cov_core, info, core_names, s2, rank_txt, G, spread, correlation)


#: a score test's widened sigma (the estimate's own, at the stepped solution) is computed only where the plain one
#: (the information at the held solution) puts the step beyond this many sigma: widening makes a sigma larger, so
#: below it no test reaches a decision limit (lrfcal.stages.markers: 4 sigma), and it saves 60 ms a calibration
SCREEN_Z = 2.0


def held_score(pb: Problem, th: FloatArray, R_ref: FloatArray, free: NDArray[np.bool_], s2: float,
                covariance_at: Callable[..., Covariance], names: Sequence[str], blocks: Blocks | None = None
                ) -> dict[str, tuple[float, float]]:
    """The score test of every unknown of ``names`` the model holds by default and this solve held
    (lrfcal.model.unknowns), each on its own (with its ``tested_with`` companion where that is held too): one
    Gauss-Newton step from the solution with it freed; per name the value it steps to and the 1-sigma the estimate
    would have there (``covariance_at(th=, free=)``: :func:`uncertainty` bound to the solve, widened for errors
    shared within a scan and within a marker and for the marker map's uncertainty; and by the reduced chi-square
    when above 1). A value many sigma from the held one says the data contradict holding it, without a second solve.

    Each is tested alone: freed together, a poorly determined one carries the others far. The plain information
    (:data:`SCREEN_Z`) as the sigma put the range scale 4.6-9.9 sigma from 1 on 4 of 70 random truths (errors
    common to a marker's returns); the widened sigma evaluated at the held solution, whose residuals carry the
    misfit under test, was 5x the estimate's on tunnel_v with ranges 1 % long, and missed it.
    ``blocks``: ``pb.blocks(th, R_ref)`` when the caller has them already (:func:`uncertainty`'s, at the same
    state: evaluated once)."""
    tested = [i for i, u in enumerate(UNKNOWNS) if u.held and u.name in names and not free[i]]
    if not tested:
        return {}
    first = int(free[:N_CORE].sum())
    beside = [j for j in {CORE_NAMES.index(UNKNOWNS[i].tested_with) for i in tested if UNKNOWNS[i].tested_with}
              if not free[j]]
    cols = np.concatenate([np.flatnonzero(free[:N_CORE]), tested, beside]).astype(np.int64)
    blocks = pb.blocks(th, R_ref) if blocks is None else blocks
    S_all, rhs_all, _ = schur(assemble(blocks, cols))
    out = {}
    for k, i in enumerate(tested):
        with_ = [j for j in beside if CORE_NAMES[j] == UNKNOWNS[i].tested_with]
        sel = np.array([*range(first), first + k, *(cols.size - len(beside) + beside.index(j) for j in with_)])
        S, rhs = S_all[np.ix_(sel, sel)], rhs_all[sel]
        col = np.sqrt(np.maximum(np.diag(S), 1e-300))
        try:
            cov = np.linalg.inv(S / np.outer(col, col)) / np.outer(col, col)
        except np.linalg.LinAlgError:
            continue
        step, sigma = float(cov[first] @ rhs), float(np.sqrt(max(s2, 1.0) * max(cov[first, first], 0.0)))
        if abs(step) > SCREEN_Z * sigma:  # the sigma the estimate would have, at the stepped solution
            freed = free.copy()
            freed[[i, *with_]] = True
            at = np.flatnonzero(freed[:N_CORE])
            full = solve_step(assemble(blocks, at), 0.0)
            stepped = th.copy()
            stepped[at] += full[:at.size]
            stepped[N_CORE:] += full[at.size:]
            var = covariance_at(th=stepped, free=freed).covariance[i, i] * max(s2, 1.0) / max(s2, 1e-12)
            sigma = float(np.sqrt(var)) if np.isfinite(var) else math.inf
        out[CORE_NAMES[i]] = (float(th[i] + step), sigma)
    return out


__all__ = ["SCREEN_Z", "Covariance", "held_score", "inflate_for_correlation", "inflate_for_markers",
           "uncertainty", "widen"]
