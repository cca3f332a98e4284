"""Stage 5a: a start that does not need a good nominal — a correspondence-free search over the DH parameters.

The association (stage 4) matches blobs to markers by their geometry in frame M, which depends on the DH
parameters: from the nominal values it works within about 3 deg of alpha and beta and 3 cm of a and b. When it does
not (the nominal is off, or the rig was assembled differently), the DH parameters are searched for without any
correspondence: each blob is one point p_M(DH) (its returns' mean range pushed 2R/3 into the sphere, mean motor
angle and bearing), and a DH set scores by how many blob-pair distances |p_i - p_j| some tape-measured marker-pair
distance explains,

    score(DH) = mean over blob pairs of exp(-(min_kl |d_ij - D_kl|)^2 / (2 tol^2)),

which is invariant to the unknown mount pose and to mirroring, and needs no ids. A grid over alpha and beta
(+-45 deg around the nominal, 1.5 deg steps) finds the basin; coordinate-wise grids over (a, b) and (alpha, beta)
with shrinking steps refine it. The few best candidates are handed back to the association and the solver, which
decide by the data (the method's promised basin: DH angles within 45 deg, a and b within 10 cm of the truth).
The same search over every attitude (``span_rad=GLOBAL_SPAN_RAD``, 16x the grid) is the coarse global start, run
by lrfcal.stages.markers when no candidate of the basin associates well. The score cannot tell the mirror twins apart,
so
its peaks come in twins (lrfcal.model.kinematics.dh_twins); the mirror check then judges them by the nominal.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from lrfcal.model.kinematics import DH, dh_twins
from lrfcal.model.unknowns import dh_difference, wrap_pi
from lrfcal.types import MarkerMap, Observations

FloatArray = NDArray[np.float64]

#: The basin the search covers around the nominal values.
ANGLE_SPAN_RAD = math.radians(45.0)
#: The span of the global search: every attitude of the scan plane.
GLOBAL_SPAN_RAD = math.pi
LENGTH_SPAN_M = 0.10


def _blob_points(obs: Observations, n_blobs: int, radius_m: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per marker sighting: mean range (pushed 2R/3 into the sphere), mean motor angle, mean bearing; (B',) each.

    Blobs of one marker seen in several passes of the sweep share their motor angle, bearing and range whatever
    the DH parameters are (within 1 deg and 3 cm): they are merged into one point, so the search works on about one
    point per marker."""
    cnt = np.bincount(obs.blob, minlength=n_blobs).astype(float)
    keep = cnt > 0
    r = np.bincount(obs.blob, obs.ranges_m, n_blobs)[keep] / cnt[keep] + 2.0 * radius_m / 3.0
    lam = np.bincount(obs.blob, obs.lambda_rad, n_blobs)[keep] / cnt[keep]
    mu = np.bincount(obs.blob, obs.mu_rad, n_blobs)[keep] / cnt[keep]
    w = cnt[keep]
    group = np.arange(r.size)
    for i in range(r.size):  # greedy: each point joins the first earlier group it matches
        for j in range(i):
            if group[j] == j and abs(lam[i] - lam[j]) < _MERGE_RAD and abs(mu[i] - mu[j]) < _MERGE_RAD \
                    and abs(r[i] - r[j]) < 0.03:
                group[i] = j
                break
    _, g = np.unique(group, return_inverse=True)
    tot = np.bincount(g, w)
    return (np.bincount(g, w * r) / tot, np.bincount(g, w * lam) / tot, np.bincount(g, w * mu) / tot)


_MERGE_RAD = math.radians(1.0)
#: at most this many point pairs score a candidate (a seeded even sample beyond)
_MAX_PAIRS = 1500


def pair_score(
    dh_grid: FloatArray, r: FloatArray, lam: FloatArray, mu: FloatArray, marker_distances: FloatArray,
    tol_m: float = 0.01, chunk: int = 64,
) -> FloatArray:
    """The module docstring's score for C candidate DH sets (C, 4) [a, alpha, b, beta] -> (C,).

    r, lam, mu (B,) per point; marker_distances (P,). Point pairs closer than 5 cm are left out; beyond
    _MAX_PAIRS pairs a seeded even sample is used. The distance to the nearest marker-pair distance comes from a
    1 mm lookup table. ``chunk`` candidates at a time (their (chunk, pairs, 3) temporaries stay in the cache: 64 is
    a third faster than 512 with 1500 pairs; the numbers do not depend on it beyond their last bits: numpy's
    vector loops treat an array's tail apart).
    """
    B = r.size
    iu = np.triu_indices(B, 1)
    if iu[0].size > _MAX_PAIRS:
        pick = np.sort(np.random.default_rng(0).choice(iu[0].size, _MAX_PAIRS, replace=False))
        iu = (iu[0][pick], iu[1][pick])
    D = np.sort(np.asarray(marker_distances, dtype=float))
    step = 0.001
    grid = np.arange(0.0, D[-1] * 3.0 + 1.0, step)
    k = np.clip(np.searchsorted(D, grid), 1, D.size - 1)
    table = np.minimum(np.abs(grid - D[k - 1]), np.abs(grid - D[k]))  # nearest marker distance, per mm
    out = np.empty(len(dh_grid))
    cl, sl = np.cos(lam), np.sin(lam)
    for s in range(0, len(dh_grid), chunk):
        g = dh_grid[s:s + chunk]
        a, al, b, be = (g[:, i:i + 1] for i in range(4))
        phi = be + mu
        ca, sa = np.cos(al), np.sin(al)
        sp = np.sin(phi)
        x = a + r * np.cos(phi)
        y = r * sp * ca - b * sa
        z = r * sp * sa + b * ca
        P = np.stack([cl * x - sl * y, sl * x + cl * y, z], -1)  # (c, B, 3)
        d = np.linalg.norm(P[:, iu[0]] - P[:, iu[1]], axis=-1)  # (c, pairs)
        near = table[np.minimum((d / step).astype(np.int64), table.size - 1)]
        valid = d > 0.05
        w = np.exp(-0.5 * (near / tol_m) ** 2) * valid
        out[s:s + chunk] = w.sum(1) / np.maximum(valid.sum(1), 1)
    return out


def dh_candidates(
    obs: Observations, n_blobs: int, markers: MarkerMap, nominal: DH, radius_m: float, n_best: int = 3,
    span_rad: float = ANGLE_SPAN_RAD,
) -> list[DH]:
    """The ``n_best`` DH sets (best first) that explain the blobs' pairwise distances, within the basin around
    ``nominal`` (module docstring), alpha and beta within ``span_rad`` of it (:data:`GLOBAL_SPAN_RAD`: every
    attitude). Empty when there are fewer than 4 blobs."""
    r, lam, mu = _blob_points(obs, n_blobs, radius_m)
    X = np.asarray(markers.positions_W, dtype=float)
    if r.size < 4 or len(X) < 3:
        return []
    D = np.sort(np.linalg.norm(X[:, None] - X[None], axis=2)[np.triu_indices(len(X), 1)])
    nom = nominal.vector()

    step = math.radians(1.5)
    g = np.arange(-span_rad, span_rad - 1e-9 if span_rad >= math.pi else span_rad + 1e-9, step)
    A, Bt = np.meshgrid(nom[1] + g, nom[3] + g, indexing="ij")
    grid = np.column_stack([np.full(A.size, nom[0]), A.ravel(), np.full(A.size, nom[2]), Bt.ravel()])
    s = pair_score(grid, r, lam, mu, D, tol_m=0.02)
    seeds: list[FloatArray] = []
    for i in np.argsort(-s):  # distinct peaks: at least 6 deg apart
        if all(np.max(np.abs(grid[i, [1, 3]] - q[[1, 3]])) > math.radians(6.0) for q in seeds):
            seeds.append(grid[i].copy())
        if len(seeds) == n_best:
            break
    refined = [(_refine(q, q if span_rad > ANGLE_SPAN_RAD else nom, r, lam, mu, D)) for q in seeds]
    refined.sort(key=lambda t: -t[1])
    found = [DH(float(v[0]), float(v[1]), float(v[2]), float(v[3])) for v, _ in refined]
    return [nearest_representative(dh, nominal) for dh in found]


def nearest_representative(dh: DH, nominal: DH) -> DH:
    """``dh`` or its turned twin (-a, -alpha, b, beta + pi: the same rig, the mount turned by pi about the motor
    axis, lrfcal.model.kinematics.dh_twins), whichever is nearer ``nominal`` (the larger of the DH differences in
    units of 10 cm and 45 deg): the result is then reported in the nominal's representative."""
    near = dh_twins(dh)[0][1] if turned_is_nearer(dh, nominal) else dh
    return DH(near.a, float(wrap_pi(near.alpha)), near.b, float(wrap_pi(near.beta)))


def turned_is_nearer(dh: DH, nominal: DH) -> bool:
    """Whether the turned twin of ``dh`` (:func:`nearest_representative`) is nearer ``nominal`` than ``dh``."""
    def far(d: DH) -> float:
        diff = np.abs(dh_difference(d.vector(), nominal.vector()))
        return float(max(diff[[0, 2]].max() / LENGTH_SPAN_M, diff[[1, 3]].max() / ANGLE_SPAN_RAD))

    return far(dh_twins(dh)[0][1]) < far(dh)


def _refine(x: FloatArray, nom: FloatArray, r: FloatArray, lam: FloatArray, mu: FloatArray, D: FloatArray
            ) -> tuple[FloatArray, float]:
    """Coordinate-wise grid refinement of (a, b) then (alpha, beta), steps shrinking, tolerance tightening."""
    x = x.copy()
    best = -1.0
    for ab_step, ang_step, tol in ((0.02, math.radians(1.0), 0.015), (0.01, math.radians(0.5), 0.01),
                                   (0.004, math.radians(0.2), 0.006)):
        for pair, step, span in (((0, 2), ab_step, 5), ((1, 3), ang_step, 4)):
            k = np.arange(-span, span + 1) * step
            U, V = np.meshgrid(k, k, indexing="ij")
            cand = np.repeat(x[None], U.size, 0)
            cand[:, pair[0]] += U.ravel()
            cand[:, pair[1]] += V.ravel()
            lo = nom - np.array([LENGTH_SPAN_M, ANGLE_SPAN_RAD, LENGTH_SPAN_M, ANGLE_SPAN_RAD]) * 1.2
            hi = nom + np.array([LENGTH_SPAN_M, ANGLE_SPAN_RAD, LENGTH_SPAN_M, ANGLE_SPAN_RAD]) * 1.2
            cand = np.clip(cand, lo, hi)
            s = pair_score(cand, r, lam, mu, D, tol_m=tol)
            i = int(np.argmax(s))
            x, best = cand[i], float(s[i])
    return x, best


__all__ = ["ANGLE_SPAN_RAD", "GLOBAL_SPAN_RAD", "LENGTH_SPAN_M", "dh_candidates", "nearest_representative",
           "pair_score", "turned_is_nearer"]
