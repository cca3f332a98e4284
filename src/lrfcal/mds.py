"""Stage 1: marker coordinates from hand-measured distances (seed paper Sec. III-C), by metric MDS.

* All pairs measured: classical (Torgerson) MDS. With D2 the squared distances and J = I - 11^T / n,
  B = -1/2 J D2 J; X = U_3 Lambda_3^(1/2) from the 3 largest eigenpairs (negative eigenvalues clipped to 0).
  Exact for noiseless Euclidean distances, up to a rigid motion including a reflection.
* Some pairs missing: initialise with classical MDS on the shortest-path completion of the distance graph,
  then minimise the weighted stress sigma(X) = sum_{i<j} w_ij (d_ij - |x_i - x_j|)^2 (w_ij = 0 for a missing
  pair) by SMACOF: X <- V^+ B(Z) Z with V = sum w_ij (e_i - e_j)(e_i - e_j)^T and B(Z)_ij = -w_ij d_ij /
  |z_i - z_j| (i != j), B_ii = -sum_{j != i} B_ij, iterated to convergence. A few seeded random starts are
  also tried and the lowest stress is kept (SMACOF only finds a local minimum).

The output frame is centred on the markers' centroid with axes along the principal axes (largest spread
first); each axis' sign is chosen so that the largest-magnitude coordinate is positive. The handedness is
arbitrary: the association stage finds whether the frame must be mirrored.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from scipy.sparse.csgraph import shortest_path
from scipy.stats import f as f_dist

from .errors import InputError
from .types import MarkerMap, TapeMeasurements

FloatArray = NDArray[np.float64]

#: planarity (smallest / largest singular value of the centred coordinates) below which markers are coplanar
COPLANAR_THRESHOLD = 0.02
#: second / first singular value below which the markers are on one line
COLLINEAR_THRESHOLD = 1e-3


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
    tape: TapeMeasurements, *, refine: bool | None = None, n_starts: int = 4, seed: int = 0
) -> MarkerMap:
    """Marker coordinates in W from tape distances.

    Args:
        tape: n marker ids and P measured pairs (repeated pairs are averaged).
        refine: run SMACOF after classical MDS; default: only when pairs are missing.
        n_starts: extra seeded random SMACOF starts when pairs are missing.
        seed: seed of those starts.
    Returns:
        MarkerMap: positions_W (n, 3) centred on the principal axes; normalised stress; rms_m over the
        measured pairs; planarity = s3 / s1 of the centred coordinates; coplanar when planarity < 0.02.
    Raises:
        InputError: fewer than 4 markers, a marker with fewer than 3 measured partners, a non-positive or
        non-finite distance, a disconnected measurement graph, or all markers on one line.
    """
    D, W = _validate(tape)
    ids = tuple(tape.marker_ids)
    n = len(ids)
    complete = bool(np.all(W + np.eye(n) > 0))
    if not complete:
        G = np.where(W > 0, D, 0.0)
        if not np.all(np.isfinite(shortest_path(G, method="D", directed=False))):
            raise InputError("tape: the measured pairs do not connect all markers")
    X3, ssr3 = _embed(D, W, 3, complete, n_starts, seed, refine)
    X2, ssr2 = _embed(D, W, 2, complete, n_starts, seed, refine)
    planar = _planar_fits_as_well(ssr2, ssr3, n_pairs=int(np.count_nonzero(np.triu(W, 1))), n=n)
    X = np.column_stack([X2, np.zeros(n)]) if planar else X3
    X, s = _principal_frame(X)
    if s[1] < COLLINEAR_THRESHOLD * s[0]:
        raise InputError("tape: all markers lie on one line; their positions are not determined in 3D")
    planarity = 0.0 if planar else float(s[2] / s[0])
    dist = np.sqrt(((X[:, None, :] - X[None, :, :]) ** 2).sum(-1))
    iu = np.triu_indices(n, 1)
    m = W[iu] > 0
    r = (D[iu] - dist[iu])[m]
    stress = float(np.sqrt((r**2).sum() / (D[iu][m] ** 2).sum()))
    return MarkerMap(
        marker_ids=ids,
        positions_W=X,
        stress=stress,
        rms_m=float(np.sqrt(np.mean(r**2))),
        planarity=planarity,
        coplanar=planar or planarity < COPLANAR_THRESHOLD,
    )


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
    return bool(f_dist.ppf(1 - p_value, n - 3, dof3) > F)


__all__ = ["COLLINEAR_THRESHOLD", "COPLANAR_THRESHOLD", "classical_mds", "marker_map", "smacof"]
