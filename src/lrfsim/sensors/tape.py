"""The person with the tape: distances between marker centres, each with Gaussian error.

measured_ij = |x_i - x_j| + sigma_m z_ij  (z ~ N(0, 1), independent per measured pair).

With ``pair_fraction`` < 1 only a random subset of the n (n - 1) / 2 pairs is measured. The subset is then
topped up until the measured graph is usable for metric MDS: every marker in at least min(4, n - 1) pairs, and
the framework infinitesimally rigid in the markers' affine hull (rank of the rigidity matrix at the true
positions = d n - d (d + 1) / 2, d = 2 for a coplanar layout, 3 otherwise), which for generic positions implies
a unique shape up to a rigid motion (Asimow and Roth 1978).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from lrfcal.errors import InputError
from lrfsim.scenario.sections import TapeConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Each marker is measured to at least this many others (or all others when there are fewer).
MIN_PAIRS_PER_MARKER = 4


@dataclass(frozen=True)
class TapeResult:
    """marker_ids (n,), pairs (P, 2) indices into marker_ids (i < j), distances_m (P,) measured."""

    marker_ids: tuple[str, ...]
    pairs: IntArray
    distances_m: FloatArray


def affine_dimension(points: FloatArray, tol_m: float = 1e-9) -> int:
    """Dimension (0-3) of the affine hull of points (n, 3)."""
    if len(points) < 2:
        return 0
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    return int(np.sum(sv > tol_m * max(1.0, float(sv[0]))))


def is_rigid(points: FloatArray, pairs: IntArray) -> bool:
    """Infinitesimal rigidity of the bar framework (points (n, 3), bars pairs (P, 2)) in its affine hull."""
    n = len(points)
    d = affine_dimension(points)
    if n <= 1:
        return True
    centred = points - points.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    q = centred @ vt[:d].T  # (n, d) coordinates in the hull
    Rm = np.zeros((len(pairs), n * d))
    diff = q[pairs[:, 0]] - q[pairs[:, 1]]
    rows = np.arange(len(pairs))
    for k in range(d):
        Rm[rows, pairs[:, 0] * d + k] = diff[:, k]
        Rm[rows, pairs[:, 1] * d + k] = -diff[:, k]
    need = d * n - d * (d + 1) // 2
    return int(np.linalg.matrix_rank(Rm, tol=1e-9 * max(1.0, float(np.abs(Rm).max(initial=0))))) >= need


def choose_pairs(points: FloatArray, pair_fraction: float, rng: np.random.Generator) -> IntArray:
    """Pairs (P, 2), i < j, sorted: a random ``pair_fraction`` of all pairs, topped up as the module says."""
    n = len(points)
    all_pairs = np.array(list(itertools.combinations(range(n), 2)), dtype=np.int64).reshape(-1, 2)
    if pair_fraction >= 1.0 or len(all_pairs) == 0:
        return all_pairs
    order = rng.permutation(len(all_pairs))
    k = max(1, int(np.ceil(pair_fraction * len(all_pairs))))
    chosen = np.zeros(len(all_pairs), dtype=bool)
    chosen[order[:k]] = True
    need = min(MIN_PAIRS_PER_MARKER, n - 1)
    for idx in order[k:]:  # top up degrees, in the same random order
        deg = np.bincount(all_pairs[chosen].ravel(), minlength=n)
        if deg.min() >= need:
            break
        i, j = all_pairs[idx]
        if deg[i] < need or deg[j] < need:
            chosen[idx] = True
    for idx in order:  # then rigidity
        if is_rigid(points, all_pairs[chosen]):
            break
        chosen[idx] = True
    return all_pairs[chosen]


def measure_tape(marker_ids: tuple[str, ...], markers_W: FloatArray, tape: TapeConfig,
                 rng: np.random.Generator) -> TapeResult:
    """Simulate the tape measurements between the true marker centres markers_W (n, 3)."""
    pts = np.asarray(markers_W, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) != len(marker_ids):
        raise InputError(f"tape: markers_W must have shape ({len(marker_ids)}, 3), got {pts.shape}")
    pairs = choose_pairs(pts, tape.pair_fraction, rng)
    true = np.linalg.norm(pts[pairs[:, 0]] - pts[pairs[:, 1]], axis=1)
    return TapeResult(marker_ids=tuple(marker_ids), pairs=pairs,
                      distances_m=true + tape.sigma_m * rng.standard_normal(len(pairs)))


__all__ = ["MIN_PAIRS_PER_MARKER", "TapeResult", "affine_dimension", "choose_pairs", "is_rigid", "measure_tape"]
