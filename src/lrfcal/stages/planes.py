"""Targetless stage: the scene's own planes, segmented from a reprojected cloud, and their returns.

Without markers, the DH parameters are calibrated from the flatness of the scene's planar surfaces (walls, floor,
boxes): a wrong DH bends and thickens every plane of the cloud, because each return is reprojected with its own
motor angle (Kang & Doh, T-RO 2016; LM-Calibr, RA-L 2026). This module finds the planes in a cloud (in frame M)
and turns their returns into the ray-plane observations of lrfcal.estimate.solve.solve_planes.

Segmentation (:func:`segment_planes`): every point's normal and flatness from the k nearest neighbours (PCA) of the
nearest point of a coarse subsample (so that a neighbourhood spans many times the range noise);
then greedy RANSAC, each hypothesis a flat point with its own normal, scored by the points within ``thickness_m``
of the hypothesis whose normals agree within ``normal_tol_rad`` (preemptively: all hypotheses on the coarse
subsample, the few best of them on every point: Nister, "Preemptive RANSAC", ICCV 2003); the best is refitted
to its inliers (SVD), its points removed, and the search repeats until no plane has ``min_points``.
Deterministic for a given seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from lrfcal.types import ScenePlane, SurfaceReturns

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: hypotheses scored on all free points, the best by their score on the coarse subsample
_FINALISTS = 8


def point_normals(points: FloatArray, k: int = 30) -> tuple[FloatArray, FloatArray]:
    """Unit normals (P, 3) and flatness (P,) (smallest eigenvalue of the neighbourhood's covariance over their sum:
    0 for a perfect plane, 1/3 for isotropic scatter) from each point's k nearest neighbours."""
    P = np.asarray(points, dtype=float)
    k = min(k, len(P))
    _, nb = cKDTree(P).query(P, k=k)
    Q = P[nb]  # (P, k, 3), centred in place; the covariances as batched matrix products (a third faster than einsum)
    Q -= Q.mean(1, keepdims=True)
    w, V = np.linalg.eigh(np.matmul(Q.transpose(0, 2, 1), Q) / k)
    return V[:, :, 0], w[:, 0] / np.maximum(w.sum(1), 1e-300)


def nearest_of_subset(P: FloatArray, subset: IntArray, workers: int = 1) -> IntArray:
    """The index into ``subset`` (S,) (distinct rows of P) of each point's (P (K, 3)) nearest point among
    ``P[subset]``: the point itself for those of the subset (a point at distance 0; a copy of it elsewhere in the
    subset would have its label and normal, both decided by its coordinates alone), the others by a k-d tree query
    (``workers`` threads; exact whatever their number)."""
    nn = np.empty(len(P), dtype=np.int64)
    nn[subset] = np.arange(subset.size)
    rest = np.ones(len(P), dtype=bool)
    rest[subset] = False
    idx = np.flatnonzero(rest)
    if idx.size:
        nn[idx] = cKDTree(P[subset]).query(P[idx], k=1, workers=workers)[1]
    return nn


def fit_plane(points: FloatArray) -> tuple[FloatArray, float, float]:
    """Least-squares plane (normal (3,), offset, RMS distance) through points (P, 3), P >= 3."""
    c = points.mean(0)
    _, s, Vt = np.linalg.svd(points - c, full_matrices=False)
    n = Vt[2]
    return n, float(n @ c), float(s[2] / math.sqrt(len(points)))


def _in_plane_std(points: FloatArray) -> FloatArray:
    """Standard deviations (3,) of points (P, 3) along their principal axes, largest first."""
    return np.linalg.svd(points - points.mean(0), compute_uv=False) / math.sqrt(len(points))


@dataclass(frozen=True)
class Segmentation:
    """How :func:`segment_planes` finds planes.

    min_points: the fewest inliers a plane must have; max_planes: at most this many.
    normal_tol_rad: a point's normal must be this close to the plane's; max_flatness: only points this flat (or
        among the flattest 30 %) seed hypotheses.
    min_extent_m: the smaller in-plane standard deviation of a plane's points must reach this: a strip (the returns
        of a few scan lines, an edge) does not fix a plane's tilt about its own axis.
    n_hypotheses: hypotheses per plane; n_coarse: normals and flatness are computed on this many points, evenly
        spread (see the code); seed: of the hypotheses' draws.
    """

    min_points: int = 300
    max_planes: int = 30
    normal_tol_rad: float = math.radians(30.0)
    max_flatness: float = 0.02
    min_extent_m: float = 0.03
    n_hypotheses: int = 300
    n_coarse: int = 5000
    seed: int = 0


#: the segmentation unless told
DEFAULT_SEGMENTATION = Segmentation()


def segment_planes(
    points: FloatArray, *, thickness_m: float, how: Segmentation = DEFAULT_SEGMENTATION,
) -> tuple[IntArray, list[ScenePlane]]:
    """Planes of a cloud (module docstring), largest first.

    Args:
        points: (P, 3) returns in frame M.
        thickness_m: half-width of a plane's inlier slab (m): the range noise plus what a wrong DH bends a plane by.
        how: the segmentation's limits (:class:`Segmentation`).
    Returns:
        labels (P,) the plane index of each point (-1: none) and the planes (in label order).
    """
    min_points, max_planes, normal_tol_rad = how.min_points, how.max_planes, how.normal_tol_rad
    max_flatness, min_extent_m, n_hypotheses = how.max_flatness, how.min_extent_m, how.n_hypotheses
    n_coarse, seed = how.n_coarse, how.seed
    P = np.asarray(points, dtype=float)
    labels = np.full(len(P), -1, dtype=np.int64)
    planes: list[ScenePlane] = []
    if len(P) < max(min_points, 3):
        return labels, planes
    # normals from a coarse, even subsample of the cloud (its neighbourhoods span many times the range noise, which
    # a dense cloud's nearest neighbours do not), carried to every point from its nearest coarse point
    coarse = np.unique(np.linspace(0, len(P) - 1, min(len(P), n_coarse)).astype(np.int64))
    normals_c, flat_c = point_normals(P[coarse])
    nn = nearest_of_subset(P, coarse)
    normals, flat = normals_c[nn], flat_c[nn]
    is_coarse = np.zeros(len(P), dtype=bool)
    is_coarse[coarse] = True
    flat_limit = max(max_flatness, float(np.quantile(flat_c, 0.3)))
    cos_tol = math.cos(normal_tol_rad)
    rng = np.random.default_rng(seed)
    free = np.ones(len(P), dtype=bool)
    seeding = is_coarse & (flat <= flat_limit)
    while len(planes) < max_planes:
        seeds = np.flatnonzero(free & seeding)
        if seeds.size < 3:
            break
        pick = rng.choice(seeds, size=min(n_hypotheses, seeds.size), replace=False)
        cand = np.flatnonzero(free)
        Pc, Nc = P[cand], normals[cand]
        H = normals[pick]  # (h, 3)
        hd = (H * P[pick]).sum(1)
        # preemptive scoring: every hypothesis on the free coarse points, the few best of them on all free points
        cf = np.flatnonzero(free & is_coarse)
        top = np.argsort(_scores(P[cf], normals[cf], H, hd, thickness_m, cos_tol), kind="stable")[-_FINALISTS:]
        score = _scores(Pc, Nc, H[top], hd[top], thickness_m, cos_tol)
        best = int(top[int(np.argmax(score))])
        if score.max() < min_points:
            break
        n, d = H[best], float(H[best] @ P[pick[best]])
        for _ in range(3):  # refit to the inliers, then re-gate
            members = cand[(np.abs(Pc @ n - d) <= thickness_m) & (np.abs(Nc @ n) >= cos_tol)]
            if members.size < 3:
                break
            n, d, _ = fit_plane(P[members])
        if members.size < min_points or _in_plane_std(P[members])[1] < min_extent_m:  # too small, or a strip
            agree = np.abs(Nc @ H[best]) >= cos_tol
            free[cand[(np.abs(Pc @ H[best] - (H[best] @ P[pick[best]])) <= thickness_m) & agree]] = False
            continue
        if d < 0:  # orient away from the origin of M (on the motor axis, inside the scene)
            n, d = -n, -d
        _, _, rms = fit_plane(P[members])
        labels[members] = len(planes)
        free[members] = False
        planes.append(ScenePlane(n, d, int(members.size), rms, P[members].mean(0)))
    return labels, planes


def _scores(Pc: FloatArray, Nc: FloatArray, H: FloatArray, d: FloatArray, thickness_m: float, cos_tol: float,
            chunk: int = 256) -> IntArray:
    """Each hypothesis' inliers (h,): the points of Pc (c, 3) within ``thickness_m`` of the plane H_k . p = d_k whose
    normals Nc (c, 3) agree with H_k (|cos| >= cos_tol); counted in chunks of points, so that the (chunk, h)
    temporaries (0.6 MB for 300 hypotheses, written in place) stay in the cache (chunks of 1024 points took 1.7x as
    long, of 4096 4x as long on a 2-core VM; every chunk of at most 1024 points gives the products the same bits:
    OpenBLAS's small-matrix kernel). The chunks' inliers are added up element by element (a (chunk, h) count of
    the chunks, wide enough for their number) and summed over the rows once: the same integers, without a reduction
    per chunk."""
    h = H.shape[0]
    HT = np.ascontiguousarray(H.T)
    n = min(chunk, Pc.shape[0])
    n_chunks = -(-Pc.shape[0] // chunk)
    dist, cos = np.empty((n, h)), np.empty((n, h))
    ok, agree = np.empty((n, h), dtype=bool), np.empty((n, h), dtype=bool)
    counts = np.zeros((n, h), dtype=np.uint8 if n_chunks <= 255 else np.int64)
    for s in range(0, Pc.shape[0], chunk):
        P_ = Pc[s:s + chunk]
        m = P_.shape[0]
        D, C, o, a = dist[:m], cos[:m], ok[:m], agree[:m]
        np.matmul(P_, HT, out=D)
        D -= d
        np.less_equal(np.abs(D, out=D), thickness_m, out=o)
        np.matmul(Nc[s:s + chunk], HT, out=C)
        np.greater_equal(np.abs(C, out=C), cos_tol, out=a)
        o &= a
        np.add(counts[:m], o.view(np.uint8), out=counts[:m])
    return counts.sum(0, dtype=np.int64)


def plane_returns(
    labels: IntArray, planes: list[ScenePlane], scan: IntArray, beam: IntArray, lambda_rad: FloatArray,
    mu_rad: FloatArray, ranges_m: FloatArray, times_s: FloatArray | None = None,
) -> SurfaceReturns:
    """The labelled returns (labels >= 0 of the K inputs, all (K,)) as lrfcal.types.SurfaceReturns carrying
    their plane's normal and offset (the solver's start for the plane's nuisances)."""
    m = np.asarray(labels) >= 0
    surf = np.asarray(labels)[m]
    normals = np.array([p.normal for p in planes]).reshape(-1, 3)
    offsets = np.array([p.offset_m for p in planes])
    return SurfaceReturns(
        scan=np.asarray(scan)[m], beam=np.asarray(beam)[m], lambda_rad=np.asarray(lambda_rad)[m],
        mu_rad=np.asarray(mu_rad)[m], ranges_m=np.asarray(ranges_m)[m], surface=surf,
        normals=normals[surf] if surf.size else np.zeros((0, 3)),
        offsets_m=offsets[surf] if surf.size else np.zeros(0),
        times_s=None if times_s is None else np.asarray(times_s)[m],
    )


def flatness(points: FloatArray, labels: IntArray, n_planes: int) -> tuple[FloatArray, FloatArray]:
    """Each plane's points (labels == j) fitted afresh: the RMS distance (n_planes,) from their own best-fit plane
    (m; how thick the plane is in this cloud) and that plane's unit normal (n_planes, 3) (NaN with fewer than 3
    points)."""
    rms = np.full(n_planes, np.nan)
    normals = np.full((n_planes, 3), np.nan)
    for j in range(n_planes):
        m = labels == j
        if m.sum() >= 3:
            normals[j], _, rms[j] = fit_plane(points[m])
    return rms, normals


def squareness_deg(normals: FloatArray, tol_deg: float = 20.0) -> FloatArray:
    """|90 deg - angle| (deg) of every pair of planes (normals (P, 3)) within ``tol_deg`` of perpendicular: how far
    from square the corners of a box-like scene are."""
    out = []
    for i in range(len(normals)):
        for j in range(i + 1, len(normals)):
            ang = math.degrees(math.acos(min(1.0, abs(float(normals[i] @ normals[j])))))
            if abs(90.0 - ang) <= tol_deg:
                out.append(abs(90.0 - ang))
    return np.array(out)


__all__ = ["DEFAULT_SEGMENTATION", "Segmentation", "fit_plane", "flatness", "nearest_of_subset",
           "plane_returns", "point_normals", "segment_planes", "squareness_deg"]
