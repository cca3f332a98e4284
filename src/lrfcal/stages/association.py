"""Stage 4: match the blobs (marker returns reprojected into the motor frame M) to the markers (MDS frame W).

The markers carry no ids, the MDS frame may be a mirror image of the real world, some markers are missed,
some blobs are false detections and one marker may give several blobs (one per sweep pass). The method:

1. hypotheses: a blob triplet and a marker triplet whose side lengths agree within ``side_tol_m`` (looked up
   by their sorted side lengths in a k-d tree; every vertex ordering consistent with the sides is tried);
   the blob triplets are a seeded random sample of the well-conditioned ones (all sides > 2 gate, smallest
   height > gate), so the result is deterministic;
2. each hypothesis gives a proper rigid transform (Kabsch on the 3 pairs), once against the markers X and
   once against the mirrored markers X * diag(1, 1, -1); it is scored by the (weighted) number of blobs whose
   nearest marker is within ``gate_m``, ties broken by the RMS of those distances;
3. the best hypotheses are refined by alternating nearest-marker assignment (many blobs to one marker
   allowed) and weighted Kabsch over all inliers, until the assignment no longer changes.

Mirroring: a triangle and its mirror image are always related by a proper rotation, so triplets cannot tell
the handedness; the other markers do. For a coplanar layout the mirror image about the principal plane is the
layout itself, and ``mirrored`` stays False unless the mirrored fit is clearly better.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from itertools import combinations
from math import comb

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from lrfcal.errors import CalibrationError, InputError
from lrfcal.types import Association, MarkerMap, Observations, Solution

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: permutations of a triangle's vertices
_PERMS = np.array([(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)])
_MIRROR = np.array([1.0, 1.0, -1.0])


def kabsch(P: ArrayLike, Q: ArrayLike, weights: ArrayLike | None = None) -> FloatArray:
    """Rigid transform (rotation + translation, no scale, no reflection) that best maps P onto Q.

    Minimises sum_i w_i |R p_i + t - q_i|^2 (Kabsch / Umeyama without scale).

    Args:
        P: (k, 3) points, k >= 3 not collinear for a unique answer.
        Q: (k, 3) corresponding points.
        weights: (k,) non-negative weights (default all 1).
    Returns:
        T (4, 4) with Q ~ T P, i.e. q_i ~ T[:3, :3] p_i + T[:3, 3].
    """
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape:
        raise InputError(f"kabsch: expected two (k, 3) arrays of the same shape, got {P.shape} and {Q.shape}")
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float).reshape(len(P))
    if len(P) == 0 or not np.all(w >= 0) or w.sum() <= 0:
        raise InputError("kabsch: need at least one point with a positive weight")
    w = w / w.sum()
    cp, cq = w @ P, w @ Q
    H = (P - cp).T @ ((Q - cq) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cq - R @ cp
    return T


def _kabsch_batch(P: FloatArray, Q: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unweighted Kabsch for a stack: P, Q (H, k, 3) -> R (H, 3, 3), t (H, 3) with Q ~ R P + t."""
    cp, cq = P.mean(1), Q.mean(1)
    Hm = np.einsum("hki,hkj->hij", P - cp[:, None], Q - cq[:, None])
    U, _, Vt = np.linalg.svd(Hm)
    D = np.ones((len(P), 3))
    D[:, 2] = np.where(_det3(np.einsum("hji,hkj->hik", Vt, U)) < 0, -1.0, 1.0)  # the sign of det(V U^T)
    R = np.einsum("hji,hj,hkj->hik", Vt, D, U)  # V diag(D) U^T
    t = cq - np.einsum("hij,hj->hi", R, cp)
    return R, t


def _det3(M: FloatArray) -> FloatArray:
    """Determinants (H,) of 3 x 3 matrices M (H, 3, 3) by cofactors along the first row: for the rotations and
    reflections of :func:`_kabsch_batch` (+-1 to rounding) the sign np.linalg.det gives, without an LU per matrix."""
    return (M[:, 0, 0] * (M[:, 1, 1] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 1])
            - M[:, 0, 1] * (M[:, 1, 0] * M[:, 2, 2] - M[:, 1, 2] * M[:, 2, 0])
            + M[:, 0, 2] * (M[:, 1, 0] * M[:, 2, 1] - M[:, 1, 1] * M[:, 2, 0]))


def unmirror(markers: MarkerMap) -> MarkerMap:
    """The MarkerMap with its z axis negated: the frame :func:`associate` matched when ``mirrored``."""
    flip = np.tile(_MIRROR, len(markers.marker_ids))  # each marker's z negated, in the covariance too
    cov = None if markers.covariance is None else markers.covariance * np.outer(flip, flip)
    return replace(markers, positions_W=np.asarray(markers.positions_W, dtype=float) * _MIRROR, covariance=cov)


def _triangle_ok(sides: FloatArray, gate_m: float) -> NDArray[np.bool_]:
    """Well-conditioned triangles: all sides > 2 gate and smallest height (2 area / longest side) > gate.

    sides (T, 3) -> (T,) bool (Heron's formula for the area).
    """
    s = 0.5 * sides.sum(1)
    area2 = np.clip(s * (s - sides[:, 0]) * (s - sides[:, 1]) * (s - sides[:, 2]), 0.0, None)
    height = 2.0 * np.sqrt(area2) / np.maximum(sides.max(1), 1e-12)
    return (sides.min(1) > 2.0 * gate_m) & (height > gate_m)


def _sides(X: FloatArray, tri: IntArray) -> FloatArray:
    """Side lengths (|x0 - x1|, |x1 - x2|, |x2 - x0|) of triangles tri (T, 3) over points X: (T, 3)."""
    a, b, c = X[tri[:, 0]], X[tri[:, 1]], X[tri[:, 2]]
    return np.linalg.norm(np.stack([a - b, b - c, c - a], 1), axis=2)


#: distances (hypotheses x blobs x markers) :func:`_score` works on at once: its temporaries stay in the cache
#: (36 % faster than 256 hypotheses at a time with 159 blobs and 30 markers; the numbers do not depend on it)
_SCORE_BLOCK = 48_000


def _score(
    R: FloatArray, t: FloatArray, P: FloatArray, X: FloatArray, w: FloatArray, gate_m: float, chunk: int | None = None
) -> tuple[FloatArray, FloatArray]:
    """Score hypotheses R (H,3,3), t (H,3): weighted inlier count (H,) and inlier RMS (H,) of blobs P vs X, ``chunk``
    hypotheses at a time (default: about _SCORE_BLOCK distances).

    Every hypothesis' values depend on its own row only (so scoring a subset gives the same numbers).
    """
    H = len(R)
    chunk = chunk or max(1, _SCORE_BLOCK // max(len(P) * len(X), 1))
    score = np.zeros(H)
    rms = np.full(H, np.inf)
    Xc = [np.ascontiguousarray(X[:, i]) for i in range(3)]
    gate2 = gate_m**2
    # the (h, B, n) temporaries, allocated once for all chunks
    d2_buf, e_buf = (np.empty((min(chunk, H), len(P), len(X))) for _ in range(2))
    for s in range(0, H, chunk):
        Rc, tc = R[s:s + chunk], t[s:s + chunk]
        Y = np.einsum("hij,bj->hbi", Rc, P) + tc[:, None, :]  # (h, B, 3)
        # squared distance to every marker, (h, B, n), summed over x, y, z in that order (as a sum over the
        # last axis would), without the (h, B, n, 3) temporary
        d2 = np.subtract(Y[:, :, 0, None], Xc[0], out=d2_buf[:len(Rc)])
        np.multiply(d2, d2, out=d2)
        for i in (1, 2):
            e = np.subtract(Y[:, :, i, None], Xc[i], out=e_buf[:len(Rc)])
            np.multiply(e, e, out=e)
            d2 += e
        d2 = d2.min(-1)  # (h, B)
        inl = d2 < gate2
        score[s:s + chunk] = (inl * w).sum(1)
        n = inl.sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            rms[s:s + chunk] = np.where(n > 0, np.sqrt((d2 * inl).sum(1) / np.maximum(n, 1)), np.inf)
    return score, rms


def _best_hypotheses(
    R: FloatArray, t: FloatArray, P: FloatArray, X: FloatArray, w: FloatArray, gate_m: float, k: int = 5,
    n_probe: int = 8,
) -> IntArray:
    """Indices of the k best hypotheses by (score descending, RMS ascending, index): exactly
    ``np.lexsort((rms, -score))[:k]`` of :func:`_score` over all hypotheses, without scoring them all.

    Branch and bound: every hypothesis is first scored on a few probe blobs; its score on all blobs is at most
    that partial score plus the weight of the other blobs. The best bounds are scored in full, which gives a k-th
    best full score; the others are scored on the rest of the blobs block by block (:func:`_reaching`) and dropped
    as soon as their bound falls below it (they cannot enter the top k); the survivors are scored in full.
    """
    H, B = len(R), len(P)
    if 4 * k >= H or 2 * n_probe >= B:  # few: score them all
        score, rms = _score(R, t, P, X, w, gate_m)
        return np.lexsort((rms, -score))[:k]
    probe = np.unique(np.linspace(0, B - 1, n_probe).round().astype(np.int64))
    part, _ = _score(R, t, P[probe], X, w[probe], gate_m)
    rest = np.ones(B, dtype=bool)
    rest[probe] = False
    bound = part + float(w[rest].sum()) + 1e-9 * (float(w.sum()) + 1.0)  # margin for rounding
    by_bound = np.argsort(-bound, kind="stable")
    score = np.full(H, -np.inf)
    rms = np.full(H, np.inf)
    done = np.zeros(H, dtype=bool)
    first = by_bound[: max(8 * k, 64)]
    score[first], rms[first] = _score(R[first], t[first], P, X, w, gate_m)
    done[first] = True
    kth = np.sort(score[done])[::-1][min(k, int(done.sum())) - 1]
    more = _reaching(lambda c, b: _score(R[c], t[c], P[b], X, w[b], gate_m)[0], w,
                     np.flatnonzero(~done & (bound >= kth)), probe, part, kth)
    if more.size:
        score[more], rms[more] = _score(R[more], t[more], P, X, w, gate_m)
        done[more] = True
    idx = np.flatnonzero(done)  # ascending: lexsort's tie-break on the index is kept
    return idx[np.lexsort((rms[idx], -score[idx]))[:k]]


def _reaching(score: Callable[[IntArray, IntArray], FloatArray], w: FloatArray, cand: IntArray, seen: IntArray,
              part: FloatArray, kth: float, block: int = 16) -> IntArray:
    """The hypotheses ``cand`` whose full score can still reach ``kth``: their partial scores ``part`` (H,) on the
    blobs ``seen`` are extended block by block over the other blobs, and a hypothesis is dropped once that partial
    score plus the weight of the blobs not yet scored (with a margin for rounding) falls below ``kth``.
    ``score(hypotheses, blobs)``: the hypotheses' scores (k,) on those blobs; ``w`` (B,) the blobs' weights."""
    rest = np.setdiff1d(np.arange(len(w)), seen)
    got = part[cand].copy()
    left = float(w[rest].sum())
    margin = 1e-9 * (float(w.sum()) + 1.0)
    for s in range(0, rest.size, block):
        if not cand.size:
            break
        b = rest[s:s + block]
        got += score(cand, b)
        left -= float(w[b].sum())
        keep = got + left + margin >= kth
        cand, got = cand[keep], got[keep]
    return cand


def _refine(
    T: FloatArray, P: FloatArray, X: FloatArray, w: FloatArray, gate_m: float, max_iter: int = 30
) -> tuple[FloatArray, IntArray, FloatArray]:
    """ICP-style refinement: nearest marker within the gate, weighted Kabsch; returns T, assignment, dists."""
    tree = cKDTree(X)
    assign = np.full(len(P), -2)
    for _ in range(max_iter):
        Y = P @ T[:3, :3].T + T[:3, 3]
        d, j = tree.query(Y)
        new = np.where(d < gate_m, j, -1)
        if np.array_equal(new, assign):
            break
        assign = new
        m = assign >= 0
        if np.count_nonzero(m) < 3 or len(np.unique(assign[m])) < 3:
            break
        T = kabsch(P[m], X[assign[m]], w[m])
    Y = P @ T[:3, :3].T + T[:3, 3]
    d, j = tree.query(Y)
    assign = np.where(d < gate_m, j, -1).astype(np.int64)
    return T, assign, d


def associate(
    points_M: ArrayLike,
    markers: MarkerMap,
    gate_m: float = 0.05,
    blob_weights: ArrayLike | None = None,
    *,
    side_tol_m: float | None = None,
    max_triplets: int = 300,
    seed: int = 0,
) -> Association:
    """Correspondence blobs -> markers and the rigid transform T_W_M aligning the blobs onto the markers.

    Args:
        points_M: (B, 3) blob positions in the motor frame M (reprojected with the nominal DH parameters);
            rows with NaN (blobs without returns) are left unmatched (-1).
        markers: the MDS marker map (positions_W (n, 3)).
        gate_m: a blob is matched when its aligned position is within this distance of a marker.
        blob_weights: (B,) non-negative weights (e.g. blob sizes) for the score and the final fit.
        side_tol_m: tolerance on triangle side lengths for hypotheses (default: gate_m).
        max_triplets: number of blob triplets sampled (seeded) to build hypotheses.
        seed: seed of that sampling.
    Returns:
        Association: blob_to_marker (B,) marker index or -1; mirrored: True when the markers had to be
        mirrored (z negated, see :func:`unmirror`) to match; T_W_M (4, 4) with markers ~ T_W_M blobs (in the
        un-mirrored marker frame when mirrored); rms_m over matched blobs; n_matched.
    Raises:
        CalibrationError: fewer than 3 blobs or markers, or no hypothesis with 3 or more distinct matched
        markers.
    """
    P = np.asarray(points_M, dtype=float)
    X = np.asarray(markers.positions_W, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InputError(f"associate: points_M must be (B, 3), got {P.shape}")
    if gate_m <= 0:
        raise InputError(f"associate: gate_m must be > 0, got {gate_m}")
    w = np.ones(len(P)) if blob_weights is None else np.asarray(blob_weights, dtype=float).reshape(len(P))
    if np.any(w < 0) or not np.all(np.isfinite(w)):
        raise InputError("associate: blob_weights must be finite and non-negative")
    valid = np.all(np.isfinite(P), axis=1)  # NaN rows (blobs without returns) stay unmatched
    if not valid.all():
        sub = associate(P[valid], markers, gate_m, w[valid], side_tol_m=side_tol_m, max_triplets=max_triplets,
                        seed=seed)
        full = np.full(len(P), -1, dtype=np.int64)
        full[valid] = sub.blob_to_marker
        return Association(full, sub.mirrored, sub.T_W_M, sub.rms_m, sub.n_matched)
    B, n = len(P), len(X)
    if B < 3 or n < 3:
        raise CalibrationError(f"association needs >= 3 blobs and >= 3 markers, got {B} blobs, {n} markers")
    tol = gate_m if side_tol_m is None else float(side_tol_m)
    Pb, mt = _hypotheses(P, X, gate_m, tol, max_triplets, np.random.default_rng(seed))

    results = {}
    for mirrored in (False, True):
        fit = _best_fit(P, X * _MIRROR if mirrored else X, w, Pb, mt, gate_m)
        if fit is not None:
            results[mirrored] = fit
    if not results:
        raise CalibrationError("association: no alignment matches 3 or more distinct markers "
                               f"within the gate of {gate_m * 1000:.0f} mm")
    best = results.get(False)
    alt = results.get(True)
    # the mirrored frame must be clearly better (for coplanar markers both fit equally)
    mirrored = best is None or (
        alt is not None and (alt[0] > best[0] or (alt[0] == best[0] and alt[1] < 0.8 * best[1]))
    )
    fit = alt if mirrored else best
    assert fit is not None
    _, _, T, assign, d = fit
    m = assign >= 0
    return Association(
        blob_to_marker=assign.astype(np.int64),
        mirrored=bool(mirrored),
        T_W_M=T,
        rms_m=float(np.sqrt(np.mean(d[m] ** 2))),
        n_matched=int(m.sum()),
    )


def _marker_triangles(X: FloatArray, gate_m: float) -> tuple[IntArray, FloatArray]:
    """The well-conditioned marker triangles (T, 3) and their side lengths (T, 3); for tiny layouts, where none is,
    every non-degenerate one."""
    mtri = np.array(list(combinations(range(len(X)), 3)), dtype=np.int64)
    msides = _sides(X, mtri)
    keep = _triangle_ok(msides, gate_m)
    if not keep.any():  # tiny layouts: accept any non-degenerate triangle
        keep = _triangle_ok(msides, 0.0)
    mtri, msides = mtri[keep], msides[keep]
    if len(mtri) == 0:
        raise CalibrationError("association: the markers form no usable triangle (all collinear?)")
    return mtri, msides


def _blob_triangles(P: FloatArray, gate_m: float, tol: float, longest_m: float, max_triplets: int,
                    rng: np.random.Generator) -> tuple[IntArray, FloatArray]:
    """At most ``max_triplets`` well-conditioned blob triangles (T, 3), none with a side longer than the longest
    marker triangle's ``longest_m`` + tol, and their side lengths (T, 3): all of them when few, else a random
    sample (seeded ``rng``)."""
    B = len(P)
    if comb(B, 3) <= 20000:
        btri = np.array(list(combinations(range(B), 3)), dtype=np.int64)
    else:
        btri = np.sort(rng.integers(0, B, (30000, 3)), 1)
        btri = np.unique(btri[(btri[:, 0] < btri[:, 1]) & (btri[:, 1] < btri[:, 2])], axis=0)
    bsides = _sides(P, btri)
    ok = _triangle_ok(bsides, gate_m) & (bsides.max(1) < longest_m + tol)
    btri, bsides = btri[ok], bsides[ok]
    if len(btri) == 0:
        raise CalibrationError("association: the blobs form no usable triangle (fewer than 3 distinct, "
                               "well-separated blobs)")
    if len(btri) > max_triplets:
        pick = np.sort(rng.choice(len(btri), max_triplets, replace=False))
        btri, bsides = btri[pick], bsides[pick]
    return btri, bsides


def _hypotheses(P: FloatArray, X: FloatArray, gate_m: float, tol: float, max_triplets: int,
                rng: np.random.Generator) -> tuple[FloatArray, IntArray]:
    """Step 1 of the module docstring: the hypotheses' blob triangles Pb (H, 3, 3) and the marker indices mt (H, 3)
    of their vertices, in matching order: every (blob triangle, marker triangle, vertex ordering) whose sides agree
    within ``tol``."""
    mtri, msides = _marker_triangles(X, gate_m)
    tree = cKDTree(np.sort(msides, 1))  # marker triangles, keyed by sorted side lengths
    btri, bsides = _blob_triangles(P, gate_m, tol, msides.max(), max_triplets, rng)
    hits = tree.query_ball_point(np.sort(bsides, 1), r=tol, p=np.inf)
    bi = np.repeat(np.arange(len(btri)), [len(h) for h in hits])
    mi = np.fromiter((j for h in hits for j in h), dtype=np.int64, count=len(bi))
    if len(bi) == 0:
        raise CalibrationError("association: no marker triangle matches any blob triangle "
                               f"(side tolerance {tol * 1000:.0f} mm)")
    mperm = mtri[mi][:, _PERMS]  # (C, 6, 3)
    C = len(bi)
    ps = _sides(X, mperm.reshape(-1, 3)).reshape(C, 6, 3)
    good = np.abs(ps - bsides[bi][:, None, :]).max(-1) < tol  # (C, 6)
    ci, pi = np.nonzero(good)
    return P[btri[bi[ci]]], mperm[ci, pi]


def _best_fit(P: FloatArray, X: FloatArray, w: FloatArray, Pb: FloatArray, mt: IntArray, gate_m: float
              ) -> tuple[float, float, FloatArray, IntArray, FloatArray] | None:
    """Steps 2 and 3 of the module docstring against markers X (mirrored or not): the best refined hypothesis as
    (weighted inlier count, inlier RMS [m], T (4, 4), assignment (B,), distances (B,)), best by count then RMS;
    None when none matches 3 or more distinct markers."""
    R, t = _kabsch_batch(Pb, X[mt])
    order = _best_hypotheses(R, t, P, X, w, gate_m, k=5)  # best few, refined
    cand = []
    for h in order:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R[h], t[h]
        T, assign, d = _refine(T, P, X, w, gate_m)
        m = assign >= 0
        sc = float(w[m].sum())
        r = float(np.sqrt(np.mean(d[m] ** 2))) if m.any() else np.inf
        if len(np.unique(assign[m])) >= 3:
            cand.append((sc, r, T, assign, d))
    return max(cand, key=lambda c: (c[0], -c[1])) if cand else None


def inconsistent_blobs(matched: Observations, sol: Solution, markers: MarkerMap, range_sigma_m: float,
                        max_outlier_share: float = 0.5, floor_m: float = 0.005) -> tuple[np.ndarray, str]:
    """Blobs (indices) that disagree with the marker map, and why in words.

    First the blobs most of whose returns the solver dropped as beyond 4 sigma (matched to the wrong marker);
    else the one marker whose returns sit, on average, furthest from its tape position beyond both ``floor_m`` and
    4 sigma of that mean (sigma_r / sqrt(the number of scans seeing it)): a marker moved after taping leaves the
    tape consistent, so only its returns can tell, and their mean offset grows with every return, unlike the
    per-return test."""
    empty = np.zeros(0, dtype=np.int64)
    if sol.inlier is None:
        return empty, ""
    wrong = [int(b) for b in np.unique(matched.blob)
             if (m := matched.blob == b).sum() >= 2 and (~sol.inlier[m]).mean() > max_outlier_share]
    if wrong:
        return np.array(wrong, dtype=np.int64), f"{len(wrong)} blobs whose returns the fit rejects unassigned"
    res = np.asarray(sol.residuals_m, dtype=float)
    worst, worst_k, worst_off = 0.0, -1, 0.0
    for k in np.unique(matched.marker):
        m = (matched.marker == k) & np.all(np.isfinite(res), axis=1)
        n_scans = len(np.unique(matched.scan[m]))
        if n_scans == 0:
            continue
        offset = float(np.linalg.norm(res[m].mean(0)))
        limit = max(floor_m, 4.0 * range_sigma_m / np.sqrt(n_scans))
        if offset > limit and offset / limit > worst:
            worst, worst_k, worst_off = offset / limit, int(k), offset
    if worst_k < 0:
        return empty, ""
    blobs = np.unique(matched.blob[matched.marker == worst_k]).astype(np.int64)
    return blobs, (f"marker {markers.marker_ids[worst_k]}: its returns sit {worst_off * 1000:.0f} mm from its tape "
                   "position on average (moved after taping?): left out")


__all__ = ["associate", "inconsistent_blobs", "kabsch", "unmirror"]
