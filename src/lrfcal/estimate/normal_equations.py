"""The least-squares engine of lrfcal.estimate.solve: normal equations assembled once per iteration from the residual
blocks,
the planes' nuisances eliminated by the Schur complement.

The whitened residual vector of a solve has three kinds of rows (:class:`Blocks`): dense rows that involve only the
core unknowns (marker returns, the design drawing's prior on the DH parameters), plane rows that involve the core
unknowns and the 3 nuisances of their own plane (lrfcal.model.plane), and one prior row per plane nuisance. So the
information H = J^T W J is arrow-shaped,

    H = [[A, B], [B^T, D]],   D = blockdiag(D_1 .. D_P) (3 x 3 per plane),

assembled in O(rows) without the dense (rows, N_CORE + 3P) Jacobian, and a (damped) step solves
(A - sum_j B_j D_j^-1 B_j^T) dx_c = -(g_c - sum_j B_j D_j^-1 g_j), dx_j = -D_j^-1 (g_j + B_j^T dx_c); the same Schur
complement is the core unknowns' marginal information with the planes unknown. Where the plane rows carry a range
pattern along the scan (lrfcal.model.range_pattern), its unknowns join the core block (:attr:`Normal.extended`: its
columns, assembled per bin by bincount, couple with every plane) and are eliminated from every result, as the
residuals take the best pattern out at every evaluation (variable projection).

:func:`levenberg_marquardt`: LM on those normal equations (J^T W J + m diag(J^T W J)) dx = -J^T W r, W the Huber
weights of the whitened residuals (or 1), stopped when every step is below ``step_tol`` of its unknown's sigma (or
when a step of a fraction of a sigma no longer lowers the cost: the minimum to within the Jacobian's accuracy).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.observations import Blocks
from lrfcal.types import Iteration

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: eigenvalues of the column-scaled information below this fraction of the largest count as rank loss (the normal
#: equations resolve singular values of J to about sqrt(machine epsilon) of the largest, not below)
RANK_TOL = 1e-15


@dataclass(frozen=True)
class PatternNormal:
    """The range pattern's unknowns (q of them, lrfcal.model.range_pattern) in the normal equations: their cross
    information with the core unknowns C_c (c, q) and with the planes' nuisances C_n (3P, q), their own E (q, q), and
    their gradient g (q,)."""

    C_c: FloatArray
    C_n: FloatArray
    E: FloatArray
    g: FloatArray


@dataclass(frozen=True)
class Normal:
    """H and g = J^T W r over the free core unknowns (A (c, c), g_c (c,)) and every plane's nuisances
    (B (c, 3P), D (P, 3, 3), g_n (3P,)), and the range pattern's unknowns where the plane rows have one (eliminated
    from every result: a step, S, H and the sigmas are those of the core unknowns and planes with the pattern
    unknown)."""

    A: FloatArray
    B: FloatArray
    D: FloatArray
    g_c: FloatArray
    g_n: FloatArray
    pattern: PatternNormal | None = None

    @property
    def extended(self) -> Normal:
        """The same equations with the pattern's unknowns as core columns after the core ones (itself without a
        pattern)."""
        p = self.pattern
        if p is None:
            return self
        return Normal(np.block([[self.A, p.C_c], [p.C_c.T, p.E]]), np.vstack([self.B, p.C_n.T]), self.D,
                      np.concatenate([self.g_c, p.g]), self.g_n)

    @property
    def given_pattern(self) -> Normal:
        """The same equations with the pattern held at the value the residuals take out (itself without a
        pattern)."""
        return Normal(self.A, self.B, self.D, self.g_c, self.g_n)

    def dense(self) -> tuple[FloatArray, FloatArray]:
        """The full H (c + 3P, c + 3P) and g (c + 3P,) (the pattern's unknowns eliminated)."""
        if self.pattern is not None:
            c, q = self.A.shape[0], self.pattern.g.size
            H, g = self.extended.dense()
            return _eliminate(H, g, np.arange(c, c + q))
        c, P = self.A.shape[0], self.D.shape[0]
        H = np.zeros((c + 3 * P, c + 3 * P))
        H[:c, :c] = self.A
        H[:c, c:] = self.B
        H[c:, :c] = self.B.T
        for j in range(P):
            H[c + 3 * j:c + 3 * j + 3, c + 3 * j:c + 3 * j + 3] = self.D[j]
        return H, np.concatenate([self.g_c, self.g_n])


def _eliminate(H: FloatArray, g: FloatArray, idx: IntArray) -> tuple[FloatArray, FloatArray]:
    """H (n, n) and g (n,) with the unknowns ``idx`` eliminated (their Schur complement): the information and
    gradient of the others with those unknown, (n - idx.size, ...)."""
    keep = np.setdiff1d(np.arange(H.shape[0]), idx)
    H_ok, H_oi = H[np.ix_(keep, keep)], H[np.ix_(keep, idx)]
    X = np.linalg.solve(H[np.ix_(idx, idx)], np.column_stack([H_oi.T, g[idx]]))
    S = H_ok - H_oi @ X[:, :-1]
    return 0.5 * (S + S.T), g[keep] - H_oi @ X[:, -1]


def plane_segments(plane: IntArray, n_planes: int) -> tuple[IntArray, IntArray]:
    """A stable ordering of the rows by plane and each plane's [start, stop) in it."""
    order = np.argsort(plane, kind="stable")
    bounds = np.searchsorted(plane[order], np.arange(n_planes + 1))
    return order, bounds


def assemble(b: Blocks, core: IntArray, w_dense: FloatArray | None = None, w_plane: FloatArray | None = None
             ) -> Normal:
    """The normal equations of :class:`Blocks` over the core columns ``core`` (and all nuisances), each row weighted
    by w (None: 1)."""
    assert b.J_dense is not None and b.Jc_plane is not None and b.Jn_plane is not None
    Jd = b.J_dense[:, core]
    WJd = Jd if w_dense is None else Jd * w_dense[:, None]
    wr_d = b.r_dense if w_dense is None else b.r_dense * w_dense
    Jc = b.Jc_plane[:, core]
    Jn = b.Jn_plane
    WJc = Jc if w_plane is None else Jc * w_plane[:, None]
    WJn = Jn if w_plane is None else Jn * w_plane[:, None]
    wr_p = b.r_plane if w_plane is None else b.r_plane * w_plane
    A = Jd.T @ WJd + Jc.T @ WJc
    g_c = Jd.T @ wr_d + Jc.T @ wr_p
    P, c = b.n_planes, core.size
    B, D, g_n = np.zeros((c, 3 * P)), np.zeros((P, 3, 3)), np.zeros(3 * P)
    order, bounds = b.segments if b.segments is not None else plane_segments(b.plane, P)
    # the plane rows sorted by plane once (each plane's rows then a slice, not a gather per plane); rows already in
    # plane order (lrfcal.stages.surfaces makes them so) are copied instead, to the gather's C-ordered arrays (the
    # products below see the same layout, and two arrays where the gather made two: never the same buffer twice,
    # which matmul would take as J^T J and compute otherwise)
    if order.size and order[0] == 0 and order[-1] == order.size - 1 and np.array_equal(order, np.arange(order.size)):
        Jc_s, Jn_s, WJn_s, wr_s = (np.array(x, order="C") for x in (Jc, Jn, WJn, wr_p))
    else:
        Jc_s, Jn_s, WJn_s, wr_s = Jc[order], Jn[order], WJn[order], wr_p[order]
    for j in range(P):
        if bounds[j] == bounds[j + 1]:
            continue
        rows = slice(bounds[j], bounds[j + 1])
        Jn_j, WJn_j = Jn_s[rows], WJn_s[rows]
        B[:, 3 * j:3 * j + 3] = Jc_s[rows].T @ WJn_j
        D[j] = Jn_j.T @ WJn_j
        g_n[3 * j:3 * j + 3] = Jn_j.T @ wr_s[rows]
    if b.w_prior is not None and b.r_prior is not None:
        D[:, [0, 1, 2], [0, 1, 2]] += (b.w_prior ** 2).reshape(P, 3)
        g_n += b.w_prior * b.r_prior
    return Normal(A, B, D, g_c, g_n,
                  None if b.pattern is None or not b.pattern.q else _pattern_normal(b, core, w_plane))


def _pattern_normal(b: Blocks, core: IntArray, w: FloatArray | None) -> PatternNormal:
    """The range pattern's part of the normal equations of ``b`` over ``core``, each plane row weighted by w."""
    assert b.pattern is not None and b.Jc_plane is not None and b.Jn_plane is not None
    pr, P = b.pattern, b.n_planes
    ww = np.ones(b.r_plane.size) if w is None else w
    C_c = np.stack([pr.sums(b.Jc_plane[:, col] * ww) for col in core]) if core.size else np.zeros((0, pr.q))
    n_bins = pr.Z.shape[0]
    C_n = np.zeros((3 * P, pr.q))
    for i in range(3):
        per_plane = np.bincount(b.plane * n_bins + pr.bins, weights=b.Jn_plane[:, i] * ww, minlength=P * n_bins)
        C_n[i::3] = pr.value * (per_plane.reshape(P, n_bins) @ pr.Z)
    return PatternNormal(C_c, C_n, pr.gram(w), pr.sums(ww * b.r_plane))


def schur(N: Normal, damp: float = 0.0) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The planes eliminated from (H + damp diag H): the reduced matrix S (c, c), the reduced right-hand side of
    S dx_c = rhs, and the per-plane inverses D_j^-1 (P, 3, 3) (pseudo-inverses for planes without information); the
    range pattern's unknowns eliminated as well."""
    if N.pattern is None:
        return _eliminated(N, damp)[:3]
    S, rhs, Dinv = _eliminated(N.extended, damp)[:3]
    c = N.A.shape[0]
    S_c, rhs_c = _eliminate(S, -rhs, np.arange(c, S.shape[0]))
    return S_c, -rhs_c, Dinv


def _eliminated(N: Normal, damp: float) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`schur`'s (S, rhs, D^-1) and the products B_j D_j^-1 side by side (c, 3P) they are made of."""
    A = N.A + damp * np.diag(np.maximum(np.diag(N.A), 1e-300)) if damp else N.A
    D = N.D.copy()
    if damp:
        idx = np.arange(3)
        D[:, idx, idx] += damp * np.maximum(N.D[:, idx, idx], 1e-300)
    Dinv = np.zeros_like(D)
    has = N.D.any(axis=(1, 2))  # a plane without rows (the robust passes left none) has no information: D_j^-1 = 0
    if has.any():
        Dinv[has] = np.linalg.pinv(D[has], rcond=1e-12)
    BDi = _times_blocks(N.B, Dinv)  # (c, 3P): B_j D_j^-1 side by side
    S = A - BDi @ N.B.T
    return 0.5 * (S + S.T), BDi @ N.g_n - N.g_c, Dinv, BDi


def _times_blocks(B: FloatArray, blocks: FloatArray) -> FloatArray:
    """B (c, 3P) times the block-diagonal matrix of ``blocks`` (P, 3, 3): B_j blocks_j side by side (c, 3P), in one
    batched product (the planes' loop of the Schur complement)."""
    c, P = B.shape[0], blocks.shape[0]
    return np.matmul(B.reshape(c, P, 3).transpose(1, 0, 2), blocks).transpose(1, 0, 2).reshape(c, 3 * P)


def solve_step(N: Normal, damp: float) -> FloatArray:
    """The LM step (c + 3P,) of the damped normal equations, core first (the range pattern's part of the step is
    not kept: the residuals take the best pattern out at every evaluation, lrfcal.model.range_pattern)."""
    if N.pattern is not None:
        return _pattern_dropped(N, solve_step(N.extended, damp))
    S, rhs, Dinv = schur(N, damp)
    dx_c = np.linalg.solve(S, rhs)
    v = (N.g_n + N.B.T @ dx_c).reshape(-1, 3, 1)  # per plane: dx_j = -D_j^-1 (g_j + B_j^T dx_c)
    return np.concatenate([dx_c, -np.matmul(Dinv, v).ravel()])


def _pattern_dropped(N: Normal, v: FloatArray) -> FloatArray:
    """A vector (c + q + 3P,) over :attr:`Normal.extended`'s unknowns without the pattern's q: (c + 3P,)."""
    assert N.pattern is not None
    c, q = N.A.shape[0], N.pattern.g.size
    return np.concatenate([v[:c], v[c + q:]])


def marginal_sigma(N: Normal) -> FloatArray:
    """The 1-sigma (c + 3P,) of every unknown from the undamped information (pseudo-inverse where singular), the
    range pattern unknown."""
    if N.pattern is not None:
        return _pattern_dropped(N, marginal_sigma(N.extended))
    S, _, Dinv, BDi = _eliminated(N, 0.0)
    Sinv = np.linalg.pinv(S)
    # per plane: diag(D_j^-1 + (B_j D_j^-1)^T S^-1 B_j D_j^-1), for all planes at once
    var_n = np.diagonal(Dinv, axis1=1, axis2=2).ravel() + (BDi * (Sinv @ BDi)).sum(0)
    return np.sqrt(np.maximum(np.concatenate([np.diag(Sinv), var_n]), 1e-300))


#: a barely damped step below ``stall_tol`` sigma that lowers the cost (0.5 chi^2) by less than this is converged:
#: a Gauss-Newton step to the minimum of a quadratic cost lowers it by 0.5 d^2 for a step of d sigma (Mahalanobis,
#: at least the largest marginal ratio), so such a step zig-zags across a valley the Jacobian does not describe to
#: that accuracy (the sphere model's rim) within a tenth of a sigma of its floor
FLAT_COST = 1e-5


def _add_step(th: FloatArray, free: IntArray, step: FloatArray) -> FloatArray:
    """th with ``step`` (free.size,) added to its entries ``free`` (the default step of :func:`levenberg_marquardt`)."""
    trial = th.copy()
    trial[free] += step
    return trial


@dataclass(frozen=True)
class Limits:
    """When a pass of :func:`levenberg_marquardt` stops: after ``max_iter`` iterations, or converged when a step is
    below ``step_tol`` of every unknown's sigma, or when a barely damped step below ``stall_tol`` sigma does not
    lower the cost or lowers it by less than :data:`FLAT_COST`."""

    max_iter: int = 60
    step_tol: float = 1e-3
    stall_tol: float = 0.1


#: the limits of a pass unless told
DEFAULT_LIMITS = Limits()


def levenberg_marquardt(
    th0: FloatArray, evaluate: Callable[[FloatArray, bool], Blocks], core: IntArray, n_core: int,
    huber: float | None = None, limits: Limits = DEFAULT_LIMITS,
    retract: Callable[[FloatArray, IntArray, FloatArray], FloatArray] | None = None,
    log: list[Iteration] | None = None,
) -> tuple[FloatArray, int, bool]:
    """Minimise the (Huber) cost of ``evaluate(th, jac)`` over the core unknowns ``core`` and every nuisance (the
    entries of th from ``n_core`` on). Returns (th, evaluations, converged): converged as ``limits`` say
    (:class:`Limits`), or when no step lowers the cost any more (at the minimum).
    ``retract(th, free, step)``: th moved by a step (free.size,) over the entries ``free`` of th, for unknowns whose
    Jacobian columns are those of a chart at th rather than derivatives by th's own entries (th[free] + step when
    None). ``log``: each accepted iteration appended (:class:`Iteration`)."""
    free = np.concatenate([core, np.arange(n_core, th0.size)])
    max_iter, step_tol, stall_tol = limits.max_iter, limits.step_tol, limits.stall_tol
    th = th0.copy()
    move = retract or _add_step

    def cost(r: FloatArray) -> float:
        if huber is None:
            return float(0.5 * r @ r)
        a = np.abs(r)
        return float(np.where(a <= huber, 0.5 * r * r, huber * a - 0.5 * huber * huber).sum())

    def weights(r: FloatArray) -> FloatArray | None:
        return None if huber is None else np.minimum(1.0, huber / np.maximum(np.abs(r), 1e-300))

    b = evaluate(th, True)
    c, damp, n_eval = cost(b.residuals()), 1e-4, 1
    retried = False  # the last iteration's first step was rejected
    for _ in range(max_iter):
        N = assemble(b, core, weights(b.r_dense), weights(b.r_plane))
        sigma = marginal_sigma(N)
        first = True
        while True:
            try:
                step = solve_step(N, damp)
            except np.linalg.LinAlgError:
                step = np.full(free.size, np.nan)
            ok = bool(np.all(np.isfinite(step)))
            trial = move(th, free, step) if ok else th.copy()
            ratio = float(np.max(np.abs(step) / sigma)) if ok else np.inf
            small = ratio < step_tol
            if small and first and damp <= 1e-3:  # a negligible, barely damped step: converged, nothing to check
                if log is not None:
                    log.append(Iteration(c, ratio, damp, n_eval))
                return trial, n_eval, True
            # with its Jacobian (the next iteration's, if accepted), but not where the first step after one that
            # was rejected is tried: less damped again, it is mostly rejected too (the damping's ping-pong)
            lazy = first and retried
            b_new = evaluate(trial, not lazy) if ok else None
            c_new = cost(b_new.residuals()) if b_new is not None else np.inf
            n_eval += ok
            if c_new <= c:
                break
            if first and ratio < stall_tol and damp <= 1e-3:
                # a barely damped step of a fraction of a sigma that does not lower the cost: at the minimum to within
                # the Jacobian's own accuracy (the clock column uses the smoothed joint velocity)
                return th, n_eval, True
            first = False
            damp *= 10.0
            if damp > 1e10:
                return th, n_eval, True  # no step decreases the cost: at the minimum
        flat = first and damp <= 1e-3 and ratio < stall_tol and c - c_new < FLAT_COST
        retried = not first
        if log is not None:
            log.append(Iteration(c_new, ratio, damp, n_eval))
        th, c, damp = trial, c_new, max(damp / 10.0, 1e-9)
        if small or flat:
            return th, n_eval, True
        assert b_new is not None
        # the residuals at the accepted step are the same either way: its Jacobian, where it was not evaluated,
        # comes with the same evaluation again (not counted)
        b = evaluate(th, True) if lazy else b_new
    return th, n_eval, False


def scores_by_cluster(b: Blocks, core: IntArray, cluster_dense: IntArray, cluster_plane: IntArray,
                      pattern: PatternNormal | None = None) -> tuple[IntArray, FloatArray]:
    """For the cluster-robust (sandwich) covariance: the clusters' ids (clusters,), sorted (each prior row a
    cluster of its own, ids below every other), and G (clusters, c + 3P), per cluster the sum of J_i^T r_i over
    its rows, in that order. ``pattern``: the range pattern's part of the unweighted normal equations of ``b``
    (Normal.pattern of ``assemble(b, core)``) when the caller has it (None: computed here where ``b`` has one)."""
    assert b.J_dense is not None and b.Jc_plane is not None and b.Jn_plane is not None
    P, c = b.n_planes, core.size
    n_prior = 0 if b.r_prior is None else b.r_prior.size
    rows = np.concatenate([cluster_dense, cluster_plane, np.iinfo(np.int64).min + np.arange(n_prior)])
    ids, inv = np.unique(rows, return_inverse=True)
    n_cl = ids.size
    m, K = b.r_dense.size, b.r_plane.size
    n = c + 3 * P
    G = np.zeros((n_cl, n))
    inv_d, inv_p, inv_q = inv[:m], inv[m:m + K], inv[m + K:]
    # each column's sums per cluster by one bincount over the clusters (each bin the sum of its rows in row order,
    # never -0.0): the dense rows' and then the plane rows' added to G's zeros, as a bincount over all of G's
    # entries per column added them (its other bins exact zeros): the same bits, a fraction of the memory
    for k, col in enumerate(core):
        G[:, k] += np.bincount(inv_d, weights=b.J_dense[:, col] * b.r_dense, minlength=n_cl)
        G[:, k] += np.bincount(inv_p, weights=b.Jc_plane[:, col] * b.r_plane, minlength=n_cl)
    Gn = G[:, c:]  # (n_cl, 3P), a view: each plane row's own plane's three columns
    for i in range(3):
        Gn += np.bincount(inv_p * (3 * P) + 3 * b.plane + i, weights=b.Jn_plane[:, i] * b.r_plane,
                          minlength=n_cl * 3 * P).reshape(n_cl, 3 * P)
    if n_prior and b.w_prior is not None and b.r_prior is not None:
        G[inv_q, c + np.arange(n_prior)] += b.w_prior * b.r_prior
    if b.pattern is not None and b.pattern.q:
        # the scores of the cost with the pattern eliminated: each cluster's own pattern score taken out along the
        # pattern's cross information, G - G_z E^-1 C^T
        pr, n_bins = b.pattern, b.pattern.Z.shape[0]
        G_z = pr.value * (np.bincount(inv_p * n_bins + pr.bins, weights=b.r_plane, minlength=n_cl * n_bins)
                          .reshape(n_cl, n_bins) @ pr.Z)
        pn = pattern if pattern is not None else _pattern_normal(b, core, None)
        G -= G_z @ np.linalg.solve(pn.E, np.vstack([pn.C_c, pn.C_n]).T)
    return ids, G


__all__ = ["RANK_TOL", "Blocks", "Normal", "PatternNormal", "assemble", "levenberg_marquardt", "marginal_sigma",
           "plane_segments", "schur", "scores_by_cluster", "solve_step"]
