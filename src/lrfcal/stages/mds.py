"""Stage 1: marker coordinates from hand-measured distances (seed paper Sec. III-C), by metric MDS.

* All pairs measured: classical (Torgerson) MDS. With D2 the squared distances and J = I - 11^T / n,
  B = -1/2 J D2 J; X = U_3 Lambda_3^(1/2) from the 3 largest eigenpairs (negative eigenvalues clipped to 0).
  Exact for noiseless Euclidean distances, up to a rigid motion including a reflection.
* Some pairs missing: initialise with classical MDS on the shortest-path completion of the distance graph,
  then minimise the weighted stress sigma(X) = sum_{i<j} w_ij (d_ij - |x_i - x_j|)^2 (w_ij = 0 for a missing
  pair) by SMACOF: X <- V^+ B(Z) Z with V = sum w_ij (e_i - e_j)(e_i - e_j)^T and B(Z)_ij = -w_ij d_ij /
  |z_i - z_j| (i != j), B_ii = -sum_{j != i} B_ij, iterated to convergence. A few seeded random starts are
  also tried and the lowest stress is kept (SMACOF only finds a local minimum).

Gross errors (a misread tape) are found, not absorbed: after the fit, every measured pair's residual r_p is
studentised with its leverage h_p in the linearised fit (H = A A^+, A the Jacobian of the distances with respect
to the coordinates): z_p = r_p / (sigma sqrt(1 - h_p)), with sigma a robust (MAD) scale of r / sqrt(1 - h),
floored at the tape noise ``tape_sigma_m``. This is the first-order leave-one-out residual (Cook and
Weisberg, *Residuals and Influence in Regression*, 1982): r_p / (1 - h_p) is what the other pairs predict for
pair p, minus its measurement. The few pairs with the largest z_p are then refitted without them (SMACOF
warm-started from the current map) and the one whose exact leave-one-out z is largest is dropped if it exceeds
``k_sigma``; repeat. A drop that would leave a marker with fewer than 4 partners (3 on a coplanar layout) or
the map flexible (h_p = 1) is refused instead (:class:`CalibrationError`, naming the pair), and so is a map
whose RMS stays above ``max_rms_m`` after the drops.

The output frame is centred on the markers' centroid with axes along the principal axes (largest spread
first); each axis' sign is chosen so that the largest-magnitude coordinate is positive. The handedness is
arbitrary: the association stage finds whether the frame must be mirrored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.sparse.csgraph import shortest_path
from scipy.special import fdtri  # the F distribution's quantile (scipy.stats costs ~1 s to import)

from lrfcal.errors import CalibrationError, InputError
from lrfcal.types import DroppedPair, MarkerMap, TapeMeasurements

FloatArray = NDArray[np.float64]

#: planarity (smallest / largest singular value of the centred coordinates) below which markers are coplanar
COPLANAR_THRESHOLD = 0.02
#: second / first singular value below which the markers are on one line
COLLINEAR_THRESHOLD = 1e-3
#: tape noise assumed at least (1-sigma) in the gross-error test
TAPE_SIGMA_M = 0.001
#: a pair is dropped when its leave-one-out residual exceeds this many sigma
K_SIGMA = 5.0
#: the map is refused when its RMS over the kept pairs is still above this
MAX_RMS_M = 0.005
#: fewer redundant pairs than this: the tape noise of the map's covariance is at least TAPE_SIGMA_M
MIN_DOF_SIGMA = 10
#: pairs refitted per round (the largest first-order z)
_N_CANDIDATES = 3


def classical_mds(D: FloatArray, dim: int = 3) -> FloatArray:
    """Classical MDS of a full (n, n) distance matrix: (n, dim) coordinates (eigenvalues clipped to >= 0)."""
    n = len(D)
    J = np.eye(n) - np.full((n, n), 1.0 / n)
    Bm = -0.5 * J @ (D**2) @ J
    vals, vecs = np.linalg.eigh(0.5 * (Bm + Bm.T))
    order = np.argsort(vals)[::-1][:dim]
    return vecs[:, order] * np.sqrt(np.clip(vals[order], 0.0, None))


def smacof(
    D: FloatArray, W: FloatArray, X0: FloatArray, max_iter: int = 10000, tol: float = 1e-13
) -> tuple[FloatArray, float]:
    """Weighted SMACOF (Guttman transform) from X0.

    Args:
        D: (n, n) target distances (any value where W is 0).
        W: (n, n) symmetric non-negative weights, zero diagonal (0 for a missing pair).
        X0: (n, k) start.
    Returns:
        X (n, k), raw stress sum_{i<j} w_ij (d_ij - |x_i - x_j|)^2.
    """
    V = -W.copy()
    V[np.diag_indices_from(V)] = W.sum(1)
    Vp = np.linalg.pinv(V)
    X = np.array(X0, dtype=float)
    n, k = X.shape
    # The plain update written with preallocated buffers and no (n, n, k) temporary, for speed (a 3D fit of a
    # coplanar layout runs to max_iter): the arithmetic, and so every bit of the result, is that of
    #   dist = sqrt(((X[:, None] - X[None]) ** 2).sum(-1));  stress = 0.5 * (W * (D - dist) ** 2).sum()
    #   Bz = where(dist > 0, -W D / dist, 0), Bz_ii = -sum_j Bz_ij;  X <- V^+ (Bz X)
    nWD = -(W * D)
    Xt = np.empty((k, n))
    diff = np.empty((k, n, n))
    dist = np.empty((n, n))
    res = np.empty((n, n))
    Bz = np.zeros((n, n))
    Bz_diag = Bz.reshape(-1)[:: n + 1]  # a view of Bz's diagonal
    row = np.empty(n)
    pos = np.empty((n, n), dtype=bool)
    prev = np.inf
    stress = np.inf
    for _ in range(max_iter):
        # squared coordinate differences (k, n, n), summed over k in the order a sum over the last axis takes
        np.copyto(Xt, X.T)
        np.subtract(Xt[:, :, None], Xt[:, None, :], out=diff)
        np.multiply(diff, diff, out=diff)
        np.add.reduce(diff, axis=0, out=dist)
        np.sqrt(dist, out=dist)
        np.subtract(D, dist, out=res)
        np.multiply(res, res, out=res)
        np.multiply(W, res, out=res)
        stress = 0.5 * float(res.sum())
        if math.isfinite(prev) and prev - stress <= tol * prev:
            break
        prev = stress
        np.greater(dist, 0.0, out=pos)
        Bz.fill(0.0)
        np.divide(nWD, dist, out=Bz, where=pos)
        Bz_diag.fill(0.0)
        np.sum(Bz, axis=1, out=row)
        np.negative(row, out=Bz_diag)
        X = Vp @ (Bz @ X)
    return X, stress


def _principal_frame(X: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Centre X, rotate to principal axes, fix the axis signs; returns (X', singular values (3,))."""
    Xc = X - X.mean(0)
    _, s, Vt = np.linalg.svd(Xc, full_matrices=False)
    Y = Xc @ Vt.T
    big = np.abs(Y).argmax(0)
    Y = Y * np.where(Y[big, np.arange(Y.shape[1])] < 0, -1.0, 1.0)
    return Y, s


def _validate(tape: TapeMeasurements) -> tuple[FloatArray, FloatArray]:
    """Check the measurements; return the distance matrix D and the weight (measured) matrix W, (n, n)."""
    ids = tuple(tape.marker_ids)
    n = len(ids)
    if n < 4:
        raise InputError(f"tape: need at least 4 markers for a 3D marker map, got {n}")
    if len(set(ids)) != n:
        raise InputError("tape: marker ids are not unique")
    pairs = np.asarray(tape.pairs)
    d = np.asarray(tape.distances_m, dtype=float)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or d.shape != (len(pairs),):
        raise InputError(f"tape: pairs must be (P, 2) and distances (P,), got {pairs.shape} and {d.shape}")
    if not np.issubdtype(pairs.dtype, np.integer) or np.any(pairs < 0) or np.any(pairs >= n):
        raise InputError(f"tape: pair indices must be integers in 0..{n - 1}")
    self_pair = pairs[:, 0] == pairs[:, 1]
    if self_pair.any():
        i = int(pairs[self_pair][0, 0])
        raise InputError(f"tape: distance from marker {ids[i]} to itself")
    bad = ~np.isfinite(d) | (d <= 0)
    if bad.any():
        k = int(np.nonzero(bad)[0][0])
        i, j = pairs[k]
        raise InputError(f"tape: distance {ids[i]}-{ids[j]} must be a positive number, got {d[k]!r}")
    S = np.zeros((n, n))
    C = np.zeros((n, n))
    np.add.at(S, (pairs[:, 0], pairs[:, 1]), d)
    np.add.at(S, (pairs[:, 1], pairs[:, 0]), d)
    np.add.at(C, (pairs[:, 0], pairs[:, 1]), 1.0)
    np.add.at(C, (pairs[:, 1], pairs[:, 0]), 1.0)
    W = (C > 0).astype(float)
    D = np.where(C > 0, S / np.maximum(C, 1), 0.0)  # repeated measurements of a pair are averaged
    partners = (C > 0).sum(1)
    few = np.nonzero(partners < 3)[0]
    if few.size:
        i = int(few[0])
        raise InputError(
            f"tape: marker {ids[i]} has {int(partners[i])} measured partner(s); at least 3 are needed to fix "
            "it in 3D"
        )
    return D, W


def marker_map(
    tape: TapeMeasurements,
    *,
    refine: bool | None = None,
    n_starts: int = 4,
    seed: int = 0,
    tape_sigma_m: float = TAPE_SIGMA_M,
    k_sigma: float = K_SIGMA,
    max_rms_m: float = MAX_RMS_M,
) -> MarkerMap:
    """Marker coordinates in W from tape distances.

    Args:
        tape: n marker ids and P measured pairs (repeated pairs are averaged).
        refine: run SMACOF after classical MDS (default: yes); False: classical MDS only, and no gross-error
            test.
        n_starts: extra seeded random SMACOF starts when pairs are missing.
        seed: seed of those starts.
        tape_sigma_m: the tape noise assumed at least (floor of the robust scale of the gross-error test).
        k_sigma: a pair whose leave-one-out residual exceeds k_sigma sigma is dropped (or the map refused).
        max_rms_m: refuse a map whose RMS over the kept pairs stays above this.
    Returns:
        MarkerMap: positions_W (n, 3) centred on the principal axes; normalised stress; rms_m over the
        measured pairs kept; planarity = s3 / s1 of the centred coordinates; coplanar when planarity < 0.02;
        dropped_pairs: the gross errors left out.
    Raises:
        InputError: fewer than 4 markers, a marker with fewer than 3 measured partners, a non-positive or
        non-finite distance, a disconnected measurement graph, or all markers on one line.
        CalibrationError: a gross error that cannot be dropped (its markers would lose too many partners, or
        the map would become flexible), or a map RMS above max_rms_m after the drops; the message names the
        pairs.
    """
    D, W = _validate(tape)
    ids = tuple(tape.marker_ids)
    n = len(ids)
    complete = bool(np.all(W + np.eye(n) > 0))
    if not complete:
        G = np.where(W > 0, D, 0.0)
        if not np.all(np.isfinite(shortest_path(G, method="D", directed=False))):
            raise InputError("tape: the measured pairs do not connect all markers")
    how = _Fit(refine, n_starts, seed, tape_sigma_m, k_sigma, max_rms_m)
    try:
        return _marker_map(D, W, ids, complete, how)
    except _PoorFit:
        if complete or refine is False:
            raise
    # SMACOF with pairs missing can end in a local minimum (a marker folded over): more starts, then refuse
    return _marker_map(D, W, ids, complete, replace(how, n_starts=8 * max(n_starts, 4), seed=seed + 1))


class _PoorFit(CalibrationError):
    """The marker map's RMS stays above max_rms_m."""


@dataclass(frozen=True)
class _Fit:
    """How :func:`marker_map` fits the map and judges it (its arguments of those names)."""

    refine: bool | None
    n_starts: int
    seed: int
    tape_sigma_m: float
    k_sigma: float
    max_rms_m: float


def _marker_map(D: FloatArray, W: FloatArray, ids: tuple[str, ...], complete: bool, how: _Fit) -> MarkerMap:
    """The body of :func:`marker_map` after validation."""
    refine, n_starts, seed = how.refine, how.n_starts, how.seed
    tape_sigma_m, k_sigma, max_rms_m = how.tape_sigma_m, how.k_sigma, how.max_rms_m
    n = len(ids)
    X3, ssr3 = _embed(D, W, 3, complete, n_starts, seed, refine)
    X2, ssr2 = _embed(D, W, 2, complete, n_starts, seed, refine)
    planar = _planar_fits_as_well(ssr2, ssr3, n_pairs=int(np.count_nonzero(np.triu(W, 1))), n=n)
    dropped: list[DroppedPair] = []
    if refine is not False:
        W, dropped = _drop_gross_errors(D, W, X2 if planar else X3, ids, planar, tape_sigma_m, k_sigma)
        if dropped:  # refit from the previous fits (the drops moved the markers by little)
            X3, ssr3 = smacof(D, W, X3, max_iter=500)
            X2, ssr2 = smacof(D, W, X2, max_iter=500)
            planar = _planar_fits_as_well(ssr2, ssr3, n_pairs=int(np.count_nonzero(np.triu(W, 1))), n=n)
    X = np.column_stack([X2, np.zeros(n)]) if planar else X3
    X, s = _principal_frame(X)
    index = {m: i for i, m in enumerate(ids)}
    dropped = [  # the distance the final map puts each dropped pair at
        replace(p, predicted_m=float(np.linalg.norm(X[index[p.id_i]] - X[index[p.id_j]]))) for p in dropped
    ]
    if s[1] < COLLINEAR_THRESHOLD * s[0]:
        raise InputError("tape: all markers lie on one line; their positions are not determined in 3D")
    planarity = 0.0 if planar else float(s[2] / s[0])
    dist = np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(-1))
    iu = np.triu_indices(n, 1)
    m = W[iu] > 0
    r = (D[iu] - dist[iu])[m]
    stress = float(np.sqrt((r**2).sum() / (D[iu][m] ** 2).sum()))
    rms = float(np.sqrt(np.mean(r**2)))
    if rms > max_rms_m:
        worst = np.argsort(-np.abs(r))[:3]
        pi, pj = iu[0][m], iu[1][m]
        named = "; ".join(
            f"{ids[pi[k]]}-{ids[pj[k]]} measured {D[pi[k], pj[k]]:.3f} m, fits {dist[pi[k], pj[k]]:.3f} m "
            f"({r[k] * 1000:+.0f} mm)"
            for k in worst
        )
        raise _PoorFit(
            f"tape: the marker map fits the measured distances with an RMS of {rms * 1000:.1f} mm (more than "
            f"{max_rms_m * 1000:.1f} mm): the tape distances contradict each other; worst pairs: {named}; "
            "re-measure them"
        )
    pi, pj = iu[0][m], iu[1][m]
    dof = r.size - (2 * n - 3 if planar else 3 * n - 6)  # the map's redundancy
    sigma = float(np.sqrt((r**2).sum() / dof)) if dof > 0 else 0.0
    if dof < MIN_DOF_SIGMA:  # too few redundant pairs to trust the estimate alone
        sigma = max(sigma, tape_sigma_m)
    return MarkerMap(
        marker_ids=ids,
        positions_W=X,
        stress=stress,
        rms_m=rms,
        planarity=planarity,
        coplanar=planar or planarity < COPLANAR_THRESHOLD,
        dropped_pairs=tuple(dropped),
        covariance=map_covariance(X, pi, pj, sigma, planar),
        tape_sigma_m=sigma,
    )


def map_covariance(X: FloatArray, pi: NDArray[np.intp], pj: NDArray[np.intp], sigma_m: float, planar: bool = False
                   ) -> FloatArray:
    """The covariance (3n, 3n) of the marker coordinates X (n, 3) (of X.ravel()) fitted to the distances of the pairs
    (pi, pj) (P,) with independent tape noise ``sigma_m``: sigma^2 (A^T A)^+, A (P, n k) the distances' Jacobian with
    respect to the coordinates (k = 2 in the plane z = 0 when ``planar``: the out-of-plane ones are taken as exact).

    The pseudo-inverse leaves out the rigid motions, which distances cannot see: the covariance is that of the map
    best aligned with the true one, and a calibration's mount absorbs the rest."""
    n = len(X)
    k = 2 if planar else 3
    A = _distance_jacobian(X[:, :k], pi, pj)
    cov_k = sigma_m**2 * np.linalg.pinv(A.T @ A, rcond=1e-10, hermitian=True)
    idx = (3 * np.arange(n)[:, None] + np.arange(k)).ravel()
    cov = np.zeros((3 * n, 3 * n))
    cov[np.ix_(idx, idx)] = cov_k
    return cov


def _leverage(X: FloatArray, pi: NDArray[np.intp], pj: NDArray[np.intp]) -> FloatArray:
    """Leverages h (P,) of the measured distances |x_i - x_j| in the linearised fit of the coordinates X (n, k):
    the diagonal of A A^+ with A (P, n k) the Jacobian; h_p = 1 for a pair no other pair constrains."""
    U, sv, _ = np.linalg.svd(_distance_jacobian(X, pi, pj), full_matrices=False)
    rank = int(np.sum(sv > 1e-9 * max(float(sv[0]), 1e-300)))
    return np.clip((U[:, :rank] ** 2).sum(1), 0.0, 1.0)


def _distance_jacobian(X: FloatArray, pi: NDArray[np.intp], pj: NDArray[np.intp]) -> FloatArray:
    """(P, n k): the derivatives of the distances |x_i - x_j| of the pairs (pi, pj) with respect to the coordinates
    X (n, k) (row-major: marker i's coordinate c is column i k + c)."""
    n, k = X.shape
    diff = X[pi] - X[pj]
    u = diff / np.maximum(np.linalg.norm(diff, axis=1, keepdims=True), 1e-300)
    A = np.zeros((len(pi), n * k))
    rows = np.arange(len(pi))
    for c in range(k):
        A[rows, pi * k + c] = u[:, c]
        A[rows, pj * k + c] = -u[:, c]
    return A


def _robust_sigma(r: FloatArray, h: FloatArray, floor_m: float) -> float:
    """MAD scale of the studentised residuals r / sqrt(1 - h) (pairs with h ~ 1 left out), floored."""
    ok = h < 1 - 1e-6
    if not ok.any():
        return floor_m
    t = r[ok] / np.sqrt(1 - h[ok])
    return max(floor_m, 1.4826 * float(np.median(np.abs(t - np.median(t)))))


def _drop_gross_errors(
    D: FloatArray,
    W: FloatArray,
    X: FloatArray,
    ids: tuple[str, ...],
    planar: bool,
    floor_m: float,
    k_sigma: float,
) -> tuple[FloatArray, list[DroppedPair]]:
    """The iterative leave-one-out test of the module docstring. X (n, 2) or (n, 3) the current fit. Returns the weights
    without the dropped pairs and the drops; raises CalibrationError for a gross error that cannot be dropped."""
    n = len(D)
    dim = 2 if planar else 3
    min_partners = 3 if planar else 4
    Xk = np.array(X, dtype=float)
    W = W.copy()
    dropped: list[DroppedPair] = []
    for _ in range(max(1, int(np.count_nonzero(np.triu(W, 1))) // 4)):
        pi, pj = np.nonzero(np.triu(W, 1))
        if len(pi) <= dim * n - dim * (dim + 1) // 2:
            break  # no redundancy: nothing can be tested
        dist = np.linalg.norm(Xk[pi] - Xk[pj], axis=1)
        r = D[pi, pj] - dist
        h = _leverage(Xk, pi, pj)
        sigma = _robust_sigma(r, h, floor_m)
        free = 1 - h
        z1 = np.where(free > 1e-6, np.abs(r) / (sigma * np.sqrt(np.maximum(free, 1e-12))), 0.0)
        # candidates: first-order z beyond k (a pair other pairs barely check, h ~ 1, is never one: its
        # leave-one-out prediction is ill-conditioned and a refit may fold a marker over)
        cand = [int(c) for c in np.argsort(-z1)[:_N_CANDIDATES] if z1[c] > k_sigma]
        if not cand:
            break
        best: tuple[float, int, FloatArray, float] | None = None
        for c in cand:
            Wc = W.copy()
            Wc[pi[c], pj[c]] = Wc[pj[c], pi[c]] = 0.0
            Xc, _ = smacof(D, Wc, Xk, max_iter=500, tol=1e-12)
            pred = float(np.linalg.norm(Xc[pi[c]] - Xc[pj[c]]))
            keep = np.ones(len(pi), dtype=bool)
            keep[c] = False
            rc = D[pi[keep], pj[keep]] - np.linalg.norm(Xc[pi[keep]] - Xc[pj[keep]], axis=1)
            sc = _robust_sigma(rc, h[keep], floor_m)
            z = abs(D[pi[c], pj[c]] - pred) * np.sqrt(max(free[c], 1e-12)) / sc
            if best is None or z > best[0]:
                best = (z, c, Xc, pred)
        assert best is not None
        z, c, Xc, pred = best
        if z <= k_sigma:
            break
        i, j = int(pi[c]), int(pj[c])
        what = (
            f"tape pair {ids[i]}-{ids[j]}: measured {D[i, j]:.3f} m, the other pairs put it at {pred:.3f} m "
            f"({(D[i, j] - pred) * 1000:+.0f} mm, {z:.0f} sigma)"
        )
        partners = (W > 0).sum(1)
        if min(partners[i], partners[j]) - 1 < min_partners or free[c] < 1e-6:
            m = i if partners[i] <= partners[j] else j
            others = [
                f"{ids[pi[o]]}-{ids[pj[o]]}" for o in np.argsort(-z1)[:4] if o != c and z1[o] > k_sigma
            ]
            also = f" (also suspect: {', '.join(others)})" if others else ""
            raise CalibrationError(
                f"{what}; it cannot be dropped: marker {ids[m]} would keep {int(partners[m]) - 1} measured "
                f"partners ({min_partners} needed to fix it{' on a plane' if planar else ' in 3D'}){also}; "
                "re-measure it or measure more pairs"
            )
        W[i, j] = W[j, i] = 0.0
        Xk = Xc
        dropped.append(DroppedPair(ids[i], ids[j], float(D[i, j]), pred, float(z)))
    return W, dropped


def _embed(
    D: FloatArray, W: FloatArray, dim: int, complete: bool, n_starts: int, seed: int, refine: bool | None
) -> tuple[FloatArray, float]:
    """Metric MDS in ``dim`` dimensions: classical MDS (on shortest-path distances when pairs are missing),
    then weighted SMACOF (the least-squares fit of the measured distances). Returns (X (n, dim), raw stress)."""
    n = len(D)
    start = D if complete else shortest_path(np.where(W > 0, D, 0.0), method="D", directed=False)
    X = classical_mds(start, dim)
    if refine is False:
        dist = np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(-1))
        return X, 0.5 * float((W * (D - dist) ** 2).sum())
    X, best = smacof(D, W, X)
    rng = np.random.default_rng(seed)
    scale = float(np.sqrt((D[W > 0] ** 2).mean()))
    for _ in range(0 if complete else n_starts):
        Xr, st = smacof(D, W, rng.normal(0.0, scale / 2, (n, dim)))
        if st < best * (1 - 1e-9):
            X, best = Xr, st
    return X, best


def _planar_fits_as_well(ssr2: float, ssr3: float, n_pairs: int, n: int, p_value: float = 1e-3) -> bool:
    """F-test: do the n - 3 out-of-plane coordinates of the 3D fit explain more than tape noise would?

    Under a coplanar layout, (SSR2 - SSR3) / (n - 3) and SSR3 / (P - 3n + 6) both estimate the tape variance;
    a 3D fit of noisy coplanar distances otherwise folds the noise into centimetres of spurious depth.
    """
    dof3 = n_pairs - (3 * n - 6)
    if dof3 <= 0 or ssr3 <= 0:
        return ssr2 <= 1e-18
    F = ((ssr2 - ssr3) / (n - 3)) / (ssr3 / dof3)
    return bool(fdtri(n - 3, dof3, 1 - p_value) > F)


__all__ = ["COLLINEAR_THRESHOLD", "COPLANAR_THRESHOLD", "classical_mds", "map_covariance", "marker_map", "smacof"]
