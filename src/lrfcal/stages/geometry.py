"""Stage 8: tunnel dimensions from planes fitted to a reprojected cloud (paper Sec. V, Table III).

Planes are extracted one after another with RANSAC (numpy, seeded): hypotheses from random point triples are
scored on a random subset of the remaining points, the best one's inliers (|n.p - d| < threshold) are taken
from all remaining points, the plane is refitted by least squares (SVD) and its inliers removed. At the end
every plane is refitted once more on the points that are inliers of that plane only (points near a corner,
within the threshold of two planes, would otherwise pull each plane towards the other).

Grouping: normals are oriented away from the origin of M (offset d >= 0), so the two walls of a tunnel around
the sensor have opposite normals. Pairs of opposite, parallel planes are candidates; the two mutually
perpendicular pairs with the most support are the walls (the pair closer together) and floor/ceiling. The
plate is the best-supported remaining plane whose normal is along the tunnel axis (the cross product of the two
pair normals; ``axis_hint_M`` picks the plate ahead when there are planes at both ends).

Distances: a pair's separation uses one shared normal (the normalised difference of the two opposite normals)
and the two planes' inlier centroids projected on it; the plate distance is its offset d (the distance of M's
origin from the plate plane).

Array shapes: P points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.types import Plane, TunnelGeometry

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

MAX_POINTS = 100_000
_PARALLEL_COS = math.cos(math.radians(10.0))
_PERP_SIN = math.sin(math.radians(15.0))


@dataclass(frozen=True)
class FittedPlane:
    """A plane n . p = d (n unit, d >= 0) and the indices (into the points it was fitted on) of its inliers."""

    normal: FloatArray
    offset_m: float
    inliers: IntArray

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.size)


def fit_plane_lsq(points: FloatArray) -> tuple[FloatArray, float]:
    """Least-squares plane through (P, 3) points: unit normal (3,) with offset d >= 0 (n . p = d)."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[-1]
    d = float(n @ c)
    if d < 0:
        n, d = -n, -d
    return n, d


def _ransac(points: FloatArray, rng: np.random.Generator, threshold_m: float, n_hyp: int, n_eval: int
            ) -> tuple[FloatArray, float] | None:
    """Best plane hypothesis (normal, d) among n_hyp random triples, scored on n_eval random points."""
    P = len(points)
    if P < 3:
        return None
    tri = rng.integers(0, P, size=(n_hyp, 3))
    a, b, c = points[tri[:, 0]], points[tri[:, 1]], points[tri[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    if not np.any(ok):
        return None
    n = n[ok] / norm[ok, None]
    d = np.einsum("ij,ij->i", n, a[ok])
    ev = points[rng.integers(0, P, size=min(n_eval, P))]
    score = (np.abs(ev @ n.T - d) < threshold_m).sum(axis=0)
    k = int(np.argmax(score))
    return n[k], float(d[k])


def extract_planes(
    points: ArrayLike,
    threshold_m: float = 0.03,
    max_planes: int = 10,
    min_inliers: int | None = None,
    seed: int = 0,
    n_hyp: int = 300,
    n_eval: int = 3000,
) -> list[FittedPlane]:
    """Sequential RANSAC on (P, 3) points; returns planes by decreasing support (inlier indices into points).

    Stops when the best plane has fewer than ``min_inliers`` (default max(200, 1 % of P)) inliers.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    P = len(pts)
    if min_inliers is None:
        min_inliers = max(200, int(0.01 * P))
    rng = np.random.default_rng(seed)
    remaining = np.arange(P)
    found: list[tuple[FloatArray, float]] = []
    while len(found) < max_planes and remaining.size >= min_inliers:
        sub = pts[remaining]
        hyp = _ransac(sub, rng, threshold_m, n_hyp, n_eval)
        if hyp is None:
            break
        n, d = hyp
        mask = np.abs(sub @ n - d) < threshold_m
        if mask.sum() < min_inliers:
            break
        for _ in range(2):  # least-squares refit on the inliers, then re-select
            n, d = fit_plane_lsq(sub[mask])
            mask = np.abs(sub @ n - d) < threshold_m
        if mask.sum() < min_inliers:
            break
        found.append((n, d))
        remaining = remaining[~mask]
    if not found:
        return []
    # final refit on exclusive inliers (drop points within the threshold of two planes)
    N = np.stack([n for n, _ in found])
    D = np.array([d for _, d in found])
    member = np.abs(pts @ N.T - D) < threshold_m
    n_member = np.count_nonzero(member, axis=1)
    single = n_member == 1
    at_most_one = n_member <= 1
    planes: list[FittedPlane] = []
    for k in range(len(found)):
        idx = np.flatnonzero(member[:, k] & single)
        if idx.size < 3:
            idx = np.flatnonzero(member[:, k])
        n, d = fit_plane_lsq(pts[idx])
        idx = np.flatnonzero((np.abs(pts @ n - d) < threshold_m) & at_most_one)
        if idx.size >= 3:
            n, d = fit_plane_lsq(pts[idx])
        planes.append(FittedPlane(normal=n, offset_m=d, inliers=idx))
    planes.sort(key=lambda p: -p.n_inliers)
    return planes


def pair_separation_m(points: FloatArray, p1: FittedPlane, p2: FittedPlane) -> tuple[float, FloatArray]:
    """Distance between two opposite parallel planes with a shared normal; returns (distance, normal (3,))."""
    n = p1.normal - p2.normal  # normals point away from the origin, so they are opposite
    n = n / np.linalg.norm(n)
    o1 = float(n @ points[p1.inliers].mean(axis=0))
    o2 = float(n @ points[p2.inliers].mean(axis=0))
    return abs(o1 - o2), n


def tunnel_geometry(
    points_M: ArrayLike,
    axis_hint_M: ArrayLike | None = None,
    threshold_m: float = 0.03,
    max_points: int = MAX_POINTS,
    seed: int = 0,
) -> TunnelGeometry:
    """Width (walls), height (floor/ceiling) and plate distance of a tunnel from a cloud in frame M.

    Args:
        points_M: (P, 3) reprojected cloud [m]; subsampled (seeded) to ``max_points``.
        axis_hint_M: (3,) rough direction from M towards the plate, used to pick the plate when planes are found
            at both ends (and the axis when only one parallel pair is found).
        threshold_m: RANSAC inlier distance (about 3 sigma of the range noise).
    Returns:
        TunnelGeometry with None for dimensions whose planes were not found (e.g. a board-only scene); planes
        labelled 'wall', 'floor/ceiling', 'plate' or 'other'.
    """
    pts = np.asarray(points_M, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pts.sum()):  # a NaN or inf anywhere makes the sum non-finite; else nothing to drop
        pts = pts[np.isfinite(pts).all(axis=1)]
    rng = np.random.default_rng(seed)
    if len(pts) > max_points:
        pts = pts[rng.choice(len(pts), max_points, replace=False)]
    planes = extract_planes(pts, threshold_m=threshold_m, seed=seed)
    labels = ["other"] * len(planes)
    hint = None
    if axis_hint_M is not None:
        hint = np.asarray(axis_hint_M, dtype=np.float64).reshape(3)
        hint = hint / np.linalg.norm(hint)

    # candidate pairs: opposite, parallel normals
    pairs: list[tuple[int, int, float, FloatArray, int]] = []
    for i in range(len(planes)):
        for j in range(i + 1, len(planes)):
            if planes[i].normal @ planes[j].normal < -_PARALLEL_COS:
                sep, n = pair_separation_m(pts, planes[i], planes[j])
                pairs.append((i, j, sep, n, planes[i].n_inliers + planes[j].n_inliers))
    best: tuple[int, ...] = ()
    best_support = -1
    for a in range(len(pairs)):
        for b in range(a + 1, len(pairs)):
            pa, pb = pairs[a], pairs[b]
            if {pa[0], pa[1]} & {pb[0], pb[1]} or abs(pa[3] @ pb[3]) > _PERP_SIN:
                continue
            if pa[4] + pb[4] > best_support:
                best, best_support = (a, b), pa[4] + pb[4]
    width = height = plate_d = None
    axis: FloatArray | None = None
    if best:
        pa, pb = sorted((pairs[best[0]], pairs[best[1]]), key=lambda p: p[2])
        width, height = pa[2], pb[2]
        for k in (pa[0], pa[1]):
            labels[k] = "wall"
        for k in (pb[0], pb[1]):
            labels[k] = "floor/ceiling"
        axis = np.cross(pa[3], pb[3])
        axis /= np.linalg.norm(axis)
    elif pairs and hint is not None:
        # one pair only: the axis is perpendicular to it and (roughly) along the hint
        p = max(pairs, key=lambda q: q[4])
        for k in (p[0], p[1]):
            labels[k] = "parallel pair"
        axis = hint - (hint @ p[3]) * p[3]
        axis /= np.linalg.norm(axis)
    if axis is not None:
        cand = [k for k in range(len(planes)) if labels[k] == "other"
                and abs(planes[k].normal @ axis) > math.cos(math.radians(15.0))]
        if hint is not None:
            ahead = [k for k in cand if planes[k].normal @ hint > 0]
            cand = ahead or cand
        if cand:
            k = max(cand, key=lambda q: planes[q].n_inliers)
            labels[k] = "plate"
            plate_d = planes[k].offset_m
    out = tuple(Plane(normal=p.normal, offset_m=p.offset_m, label=lab, n_inliers=p.n_inliers)
                for p, lab in zip(planes, labels, strict=True))
    return TunnelGeometry(width_m=width, height_m=height, plate_distance_m=plate_d, planes=out)


__all__ = ["FittedPlane", "extract_planes", "fit_plane_lsq", "pair_separation_m", "tunnel_geometry"]
