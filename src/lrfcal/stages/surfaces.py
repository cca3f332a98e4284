"""Stage 6b: the surfaces the markers are mounted on, and the ordinary (non-marker) returns from them.

The paper's markers sit on planar surfaces: the board of its Gazebo study, the walls of the tunnel. A sphere of
radius R stuck on a plane has its centre R in front of it, so the plane is known in W from the MDS coordinates:
the plane through a coplanar group of marker centres, moved back by R (away from the sensor). Every beam that
hits that surface near the markers is then an observation too, a range residual against the ray-plane distance,
and there are hundreds of such beams per marker return.

Candidate planes are fitted through the marker centres (greedy RANSAC, >= 5 markers, not collinear) and kept only
if the reprojected cloud confirms them: most of the returns in a slab around the candidate, inside the markers'
extent, must lie on it. This rejects virtual planes through parallel lines of markers on different walls (the
two V arms of the tunnel_v layout are such a pair).

Which returns are used is decided by where each beam's RAY meets the plane at the current estimate (inside the
markers' extent, clear of the markers), never by its measured point: the measured point carries the range noise
along the ray, so at the far edge of the extent, where the rays meet the plane obliquely, a selection by it keeps
the returns that read short and drops those that read long. That selection was the cause of a Monte-Carlo bias
of 1.2-1.7 sigma in a and beta on tunnel_v and of 0.5-0.7 sigma in alpha and b on plane_30deg (issue 10;
``lrfsim study``). Returns beyond 80 deg of incidence are left out: a real beam's footprint is stretched along the
surface as 1 / cos(incidence) and its mixed range reads short there (the simulator's 7 sub-rays against its centre
ray alone, tunnel_v walls, no noise: < 0.03 mm below 70 deg, 0.04-0.11 mm at 70-80 deg, 0.6 mm on average at
80-85 deg). A gate at 65 deg, tried, removed no bias but half the information on alpha of tunnel_v, whose walls
are seen obliquely.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from lrfcal.model.kinematics import BeamTrig, Params, beam_rays_W_trig, beam_trig, points_W, points_W_trig
from lrfcal.model.scanner import true_returns
from lrfcal.model.unknowns import core_vector
from lrfcal.stages.sampling import hash_key
from lrfcal.types import Labels, Surface, SurfaceReturns

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: surface returns whose ray meets the plane more obliquely than this (angle between the ray and the plane's
#: normal) are not used (module docstring)
MAX_INCIDENCE_RAD = math.radians(80.0)
#: a return whose point lies farther than this from a surface is not one of its returns
_GATE_M = 0.03
#: the returns are chosen again at the joint estimate when it moves a return's point along its surface's normal by
#: more than this from where the choice saw it (:func:`moved_m`), at most ROUNDS choices in all: the gate cuts the
#: range noise's tails about the plane where the estimate that chose them puts it, so a choice made at a start some
#: centimetres off (a marker-only fit the markers do not determine: one scan line per marker) keeps the returns that
#: agree with that start (a fast one-pass sweep of tunnel_v, 36 random noises: RMS of error / sigma 1.43, 1.66,
#: 1.18, 1.42 for a, alpha, b, beta with one choice)
RESELECT_M = 0.002
ROUNDS = 3
#: a return is on a surface only where its scan line runs along it: the mean distance from the plane of the measured
#: points of this many neighbours along the scan, on either side, within half the gate of the surface's level (the
#: median distance from it of the points within the gate; :func:`observe_surfaces`). The level, not the plane: a
#: range offset, incidence bias or drift that the estimate choosing the returns does not hold yet puts every point a
#: centimetre off the plane, and judged from the plane the rule then kept, of range noise correlated along the scan,
#: the returns whose noise read short (tunnel_v_systematic at rho 0.7: 40-97 % of the candidates left out, alpha and
#: b up to 5.2 and 6.7 sigma off with exit 0; docs/trust.md).
#: Where a marker surface meets another (the tunnel's ceiling and its side wall), the other surface's returns next
#: to the corner pass the gate (their rays meet the plane, extended, just beyond the corner, inside the markers'
#: extent) and read short on one side of it: 0.75 % of a near-perpendicular spin's ceiling returns, up to 30 mm
#: below it, moved b by +2.7 mm without noise (docs/trust.md, seed 1046). The neighbours on the other surface's side
#: run away from the plane at the beam spacing (4-11 mm a beam at 1-2.5 m); on the plane their mean is the range
#: noise's over 5 returns (6.7 mm at 15 mm of noise: half the 30 mm gate is 2.2 times that)
ALONG_BEAMS = 5


@dataclass(frozen=True)
class SurfaceSelection:
    """How the surface returns are chosen (:func:`surface_returns`): at most ``max_returns``, those of lowest
    :func:`lrfcal.stages.sampling.hash_key` with ``seed``; candidates within ``gate_m`` of a surface; kept inside
    the markers' extent and ``marker_clearance_m`` from every marker; with rays, an incidence up to
    ``max_incidence_rad``."""

    max_returns: int = 40000
    seed: int = 0
    gate_m: float = _GATE_M
    marker_clearance_m: float = 0.03
    max_incidence_rad: float = MAX_INCIDENCE_RAD


#: the selection unless told
DEFAULT_SELECTION = SurfaceSelection()


@dataclass(frozen=True)
class PlaneMarkers:
    """The markers the surfaces are found by (:func:`find_surfaces`): their centres ``positions_W`` (n, 3), their
    radius, the uncertainty of their MDS coordinates (``position_sigma_m``) and of a sphere's contact with its
    surface (``mounting_sigma_m``), which set the planes' prior."""

    positions_W: FloatArray
    radius_m: float
    position_sigma_m: float = 0.001
    mounting_sigma_m: float = 0.0005


@dataclass(frozen=True)
class ReturnRows:
    """Returns as rows (P,): their scan and beam, motor angle, bearing, reported range, and laser-clock beam time
    (None: not carried)."""

    scan: IntArray
    beam: IntArray
    lambda_rad: FloatArray
    mu_rad: FloatArray
    ranges_m: FloatArray
    times_s: FloatArray | None = None


#: per-beam values of a grid of scans by beams: the (S, N) array, or a function of flat indices (K,) into it giving
#: those beams' values (K,), elementwise (the same bits as the array's)
GridValues = FloatArray | Callable[[IntArray], FloatArray]


@dataclass(frozen=True)
class ReturnGrid:
    """A recording's returns as a grid of scans (S) by beams (N): ranges_m (S, N), NaN for no return; mu_rad (S, N)
    per-scan bearings (or (N,)); lambda_rad (S, N) per-beam motor angles; labels (S, N) blob labels (>= 0 on marker
    returns, which are not surface returns); beam_times_s (S, N) laser-clock beam times (None: not carried).
    lambda_rad and beam_times_s may instead be functions of flat indices (K,) into the grid giving those beams'
    values (K,) (:data:`GridValues`): :func:`observe_surfaces` then computes them for the returns it reprojects only,
    a fraction of the grid."""

    ranges_m: FloatArray
    mu_rad: FloatArray
    lambda_rad: GridValues
    labels: Labels
    beam_times_s: GridValues | None = None


def _at_flat(values: GridValues) -> Callable[[IntArray], FloatArray]:
    """A grid's values (:data:`GridValues`) as a function of flat indices (K,) into the grid."""
    if callable(values):
        return values
    flat = np.asarray(values).ravel()
    return lambda i: flat[i]


def candidate_planes(markers_W: FloatArray, tol_m: float = 0.004, min_markers: int = 5, seed: int = 0,
                     n_trials: int = 400) -> list[tuple[FloatArray, float, IntArray]]:
    """Planes through >= ``min_markers`` marker centres (within ``tol_m``), largest first: (n, offset, idx)."""
    X = np.asarray(markers_W, dtype=float)
    rng = np.random.default_rng(seed)
    out: list[tuple[FloatArray, float, IntArray]] = []
    seen: set[tuple[int, ...]] = set()
    idx = np.array([rng.choice(len(X), 3, replace=False) for _ in range(n_trials)]).reshape(-1, 3)
    # every trial's plane at once: the normals (T, 3) and which markers lie within tol_m of each (T, n)
    normals = np.cross(X[idx[:, 1]] - X[idx[:, 0]], X[idx[:, 2]] - X[idx[:, 0]])
    norms = np.linalg.norm(normals, axis=1)
    unit = normals / np.where(norms < 1e-4, 1.0, norms)[:, None]
    near = np.abs(np.einsum("tnk,tk->tn", X[None, :, :] - X[idx[:, 0]][:, None, :], unit)) < tol_m
    for t in np.flatnonzero(norms >= 1e-4):
        members = np.flatnonzero(near[t])
        key = tuple(members.tolist())
        if members.size < min_markers or key in seen:
            continue
        seen.add(key)
        P = X[members]
        c = P.mean(0)
        _, s, Vt = np.linalg.svd(P - c)
        if s[1] < 0.1 * s[0]:  # collinear markers do not fix a plane
            continue
        out.append((Vt[2], float(Vt[2] @ c), members))
    out.sort(key=lambda p: -p[2].size)
    return out


def find_surfaces(
    markers: PlaneMarkers, sensor_W: FloatArray, cloud_W: FloatArray, *,
    margin_m: float = 0.05, slab_m: float = 0.3, on_plane_m: float = 0.03, min_support: float = 0.6,
) -> list[Surface]:
    """Marker planes confirmed by the cloud, moved R away from the sensor; disjoint in their markers.

    Args:
        markers: the marker centres (n, 3), their radius R and their uncertainties (:class:`PlaneMarkers`);
        sensor_W: (3,) a point on the sensor side (the motor frame's origin); cloud_W: (P, 3) reprojected returns
        (a subsample is enough). With n markers spread by s_i along the plane's axes, the prior is
        tilt_i ~ position_sigma / (s_i sqrt(n)), offset ~ sqrt(position_sigma^2 / n + mounting_sigma^2).
    """
    X = np.asarray(markers.positions_W, dtype=float)
    radius_m, position_sigma_m = markers.radius_m, markers.position_sigma_m
    mounting_sigma_m = markers.mounting_sigma_m
    used: set[int] = set()
    surfaces: list[Surface] = []
    for n, off, members in candidate_planes(X):
        if used & set(members.tolist()):
            continue
        if n @ sensor_W > off:  # orient the normal away from the sensor
            n, off = -n, -off
        P = X[members]
        c = P.mean(0)
        axes = np.linalg.svd(P - c)[2][:2]
        q = (P - c) @ axes.T
        lower, upper = q.min(0) - margin_m, q.max(0) + margin_m
        k = members.size
        prior = np.array([*(position_sigma_m / (q.std(0) * np.sqrt(k))),
                          np.sqrt(position_sigma_m**2 / k + mounting_sigma_m**2)])
        surface = Surface(n, off + radius_m, members, axes, c, lower, upper, prior,
                          plane_prior_jacobian(n, axes, c, q, members, len(X)))
        near = cloud_W[np.abs(cloud_W @ surface.normal - surface.offset_m) < slab_m]  # the slab, any extent
        dist, inside = _in_extent(surface, near)
        slab = dist[inside]
        if slab.size < 50 or np.count_nonzero(np.abs(slab) < on_plane_m) < min_support * slab.size:
            continue
        surfaces.append(surface)
        used |= set(members.tolist())
    return surfaces


def plane_prior_jacobian(normal: FloatArray, axes: FloatArray, centre: FloatArray, q: FloatArray,
                         members: IntArray, n_markers: int) -> FloatArray:
    """(3, 3 n_markers): the derivative of a marker plane's (u1, u2, offset) (the nuisances of
    lrfcal.model.unknowns.PlaneSet about this plane: m = n + u1 axes[0] + u2 axes[1]) with respect to the markers'
    coordinates. The plane is the least-squares fit through its members (in-plane coordinates q (k, 2) about their
    centroid ``centre``): moving member i along the normal by h_i tilts it by g = P h, P = (Q^T Q)^-1 Q^T, and
    lifts it by mean(h), so u_l = -g_l and offset = n . centre + mean(h) - g . (axes centre); moves within the
    plane change nothing to first order."""
    P = np.linalg.pinv(q)  # (2, k)
    d_offset = 1.0 / len(members) - P.T @ (axes @ centre)  # (k,)
    J = np.zeros((3, n_markers, 3))
    J[0, members] = -P[0][:, None] * normal
    J[1, members] = -P[1][:, None] * normal
    J[2, members] = d_offset[:, None] * normal
    return J.reshape(3, 3 * n_markers)


def _in_extent(surface: Surface, points_W: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Signed distances (P,) of points to the surface and whether they project inside the markers' extent."""
    dist = points_W @ surface.normal - surface.offset_m
    q = (points_W - surface.centre) @ surface.axes.T
    return dist, np.all((q >= surface.lower) & (q <= surface.upper), axis=1)


def surface_returns(
    surfaces: list[Surface], points_W: FloatArray, rows_in: ReturnRows, markers_W: FloatArray, *,
    selection: SurfaceSelection = DEFAULT_SELECTION,
    rays_W: tuple[FloatArray, FloatArray] | Callable[[IntArray], tuple[FloatArray, FloatArray]] | None = None,
    along: Callable[[IntArray, IntArray, Surface], NDArray[np.bool_]] | None = None,
) -> SurfaceReturns:
    """The returns (of the P rows ``rows_in``) on the surfaces, away from markers, at most ``max_returns`` (an even
    random subsample; the other limits too are the ``selection``'s, :class:`SurfaceSelection`). points_W (P, 3)
    are the returns reprojected with the current parameters.

    rays_W: the returns' beam origins (P, 3) and unit directions (P, 3) with the same parameters, or a function of
    row indices (k,) giving theirs. Given, a return is judged by where its ray meets the plane, not by its measured
    (noisy) point: inside the markers' extent and ``marker_clearance_m`` from every marker (a selection by the
    measured point keeps, at the far edge of the extent, the returns that read short and drops those that read
    long: a bias); and returns whose incidence (the angle between the ray and the plane's normal) exceeds
    ``max_incidence_rad`` are left out. Without it, the measured points decide and every incidence is kept.

    The subsample is the ``max_returns`` accepted returns of lowest :func:`lrfcal.stages.sampling.hash_key` (ties:
    surface by surface, in row order), as :func:`lrfcal.stages.sampling.hash_sample` of all the accepted ones would
    choose; the candidates within ``gate_m`` of a surface are judged in that order, in batches, until enough are
    accepted, so the rays of most are never needed. ``along(scan, beam, surface)``: (k,) whether the scan line about
    each return (its scan and beam (k,)) runs along the surface (:data:`ALONG_BEAMS`; None: not judged), asked last,
    of the candidates the other rules accept."""
    sel = selection
    max_returns, seed, gate_m = sel.max_returns, sel.seed, sel.gate_m
    marker_clearance_m, max_incidence_rad = sel.marker_clearance_m, sel.max_incidence_rad
    scan, beam, lambda_rad, mu_rad = rows_in.scan, rows_in.beam, rows_in.lambda_rad, rows_in.mu_rad
    ranges_m, times_s = rows_in.ranges_m, rows_in.times_s
    tree = cKDTree(np.asarray(markers_W))
    cos_max = math.cos(max_incidence_rad)
    rays = (lambda i: (rays_W[0][i], rays_W[1][i])) if isinstance(rays_W, tuple) else rays_W
    # every (row, surface) candidate, surface by surface in row order: the order of the ties
    cand = [np.flatnonzero(np.abs(points_W @ s.normal - s.offset_m) < gate_m) for s in surfaces]
    rows = np.concatenate(cand) if cand else np.zeros(0, dtype=np.int64)
    which = np.concatenate([np.full(c.size, k) for k, c in enumerate(cand)]) if cand else np.zeros(0, dtype=np.int64)
    order = np.argsort(hash_key(np.asarray(scan)[rows], np.asarray(beam)[rows], seed), kind="stable")
    accepted: list[IntArray] = []
    n_acc, batch = 0, max(4 * max_returns, 1024)
    for b0 in range(0, order.size, batch):
        pos = order[b0:b0 + batch]  # positions in (rows, which), in hash order
        ok = np.zeros(pos.size, dtype=bool)
        o = d = None
        if rays is not None:
            o, d = rays(rows[pos])
        for k, s in enumerate(surfaces):
            m = np.flatnonzero(which[pos] == k)
            if rays is None or o is None or d is None:
                at = points_W[rows[pos[m]]]
            else:  # the ray's intersection with the plane: o + t d, t = (offset - n.o) / n.d
                dn = d[m] @ s.normal
                m = m[np.abs(dn) >= cos_max]
                om, dm = o[m], d[m]
                at = om + ((s.offset_m - om @ s.normal) / (dm @ s.normal))[:, None] * dm
            q = (at - s.centre) @ s.axes.T
            inside = np.all((q >= s.lower) & (q <= s.upper), axis=1)
            m, at = m[inside], at[inside]
            # the nearest marker's distance, searched only within the clearance (beyond it: inf, which passes as
            # the distance itself would; within it the same distance): the same decisions, a shorter search
            m = m[tree.query(at, distance_upper_bound=marker_clearance_m)[0] >= marker_clearance_m]
            if along is not None:
                m = m[along(np.asarray(scan)[rows[pos[m]]], np.asarray(beam)[rows[pos[m]]], s)]
            ok[m] = True
        accepted.append(pos[ok][:max_returns - n_acc])
        n_acc += accepted[-1].size
        if n_acc >= max_returns:
            break
    # chosen by the beam itself, not by its position among the candidates: a slightly different estimate, which
    # moves a few returns across the gate, keeps the same subsample of the others, so every start reaches the same
    # solution
    pick = np.sort(np.concatenate(accepted)) if accepted else np.zeros(0, dtype=np.int64)
    idx, surf = rows[pick], which[pick]
    normals = np.array([s.normal for s in surfaces]).reshape(-1, 3)
    offsets = np.array([s.offset_m for s in surfaces])
    return SurfaceReturns(
        scan=np.asarray(scan)[idx], beam=np.asarray(beam)[idx], lambda_rad=np.asarray(lambda_rad)[idx],
        mu_rad=np.asarray(mu_rad)[idx], ranges_m=np.asarray(ranges_m)[idx], surface=surf,
        normals=normals[surf] if surf.size else np.zeros((0, 3)), offsets_m=offsets[surf] if surf.size else np.zeros(0),
        times_s=None if times_s is None else np.asarray(times_s)[idx],
    )


__all__ = ["DEFAULT_SELECTION", "GridValues", "PlaneMarkers", "ReturnGrid", "ReturnRows", "SurfaceSelection",
           "candidate_planes", "find_surfaces", "surface_returns"]


def level_m(surface: Surface, points_W: FloatArray, gate_m: float) -> float:
    """The surface's level for the scan-line rule (:data:`ALONG_BEAMS`): the median signed distance from its plane of
    the ``points_W`` (n, 3) within ``gate_m`` of it (0 without any). A corner's few returns do not move it; computed on
    one fixed sample, it leaves the returns chosen independent of the fraction of rows judged."""
    h = points_W @ surface.normal - surface.offset_m
    near = np.abs(h) < gate_m
    return float(np.median(h[near])) if near.any() else 0.0


def observe_surfaces(
    grid: ReturnGrid, markers: PlaneMarkers, params: Params, *, selection: SurfaceSelection = DEFAULT_SELECTION,
    intrinsics: Mapping[str, float] | None = None,
) -> tuple[list[Surface], SurfaceReturns]:
    """Find the marker-carrying surfaces and their returns in a recording.

    Args:
        grid: the recording's returns, scans by beams, with their blob labels (marker returns excluded) and beam
            times (carried with the returns, for the clock offset) (:class:`ReturnGrid`);
        markers: the markers the surfaces are found by (:class:`PlaneMarkers`; their uncertainty sets the planes'
            prior);
        params: lrfcal.model.kinematics.Params used to reproject (the marker-only estimate);
        selection: which returns are kept (:class:`SurfaceSelection`; the incidence judged by ray directions from
            ``params``);
        intrinsics: the estimate's intrinsics by name (lrfcal.model.unknowns; the others at their start), with which
            the returns are reprojected (a range scale found by the markers, say); the returns keep their reported
            values.
    """
    ranges_m, mu_rad, lambda_rad, beam_times_s = grid.ranges_m, grid.mu_rad, grid.lambda_rad, grid.beam_times_s
    max_returns, seed = selection.max_returns, selection.seed
    valid = np.isfinite(ranges_m) & (grid.labels < 0)
    flat = np.flatnonzero(valid)  # the valid returns' flat indices, row-major
    scan = flat // valid.shape[1]  # their scans and beams: np.nonzero's, at half its cost on the 2-D mask
    beam = flat - scan * valid.shape[1]
    mu_all = np.asarray(mu_rad)
    lam_at, r_f = _at_flat(lambda_rad), np.asarray(ranges_m).ravel()
    mu_f = mu_all.ravel() if mu_all.ndim == 2 else None
    times_at = None if beam_times_s is None else _at_flat(beam_times_s)

    def take(rows: IntArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """motor angles, bearings and ranges of the valid returns ``rows`` (gathered only for those rows)"""
        i = flat[rows]
        return lam_at(i), (mu_all[beam[rows]] if mu_f is None else mu_f[i]), r_f[i]

    th = core_vector(params.dh, intrinsics or {})
    sensor_W = params.mount.matrix()[:3, 3]
    row_of = np.full(valid.shape, -1, dtype=np.int64)  # each cell's valid return (-1: none)
    row_of.ravel()[flat] = np.arange(flat.size)

    def along(at_scan: IntArray, at_beam: IntArray, surface: Surface) -> NDArray[np.bool_]:
        """(k,) whether the scan line about each return (its scan and beam (k,)) runs along ``surface``
        (:data:`ALONG_BEAMS`): on either side, the mean distance from its plane of the neighbours that have a return
        within half the gate of the surface's level (a side without one passes)."""
        offsets = np.concatenate([-np.arange(1, ALONG_BEAMS + 1), np.arange(1, ALONG_BEAMS + 1)])
        nb_beam = at_beam[:, None] + offsets[None, :]
        inside = (nb_beam >= 0) & (nb_beam < valid.shape[1])
        nb = np.full(nb_beam.shape, -1, dtype=np.int64)
        nb[inside] = row_of[np.broadcast_to(at_scan[:, None], nb_beam.shape)[inside], nb_beam[inside]]
        have = nb >= 0
        need, back = np.unique(nb[have], return_inverse=True)
        lam_n, mu_n, r_n = take(need)
        r_n, lam_n, mu_n = true_returns(th, r_n, lam_n, mu_n)
        dist = np.zeros(nb.shape)
        dist[have] = (points_W(r_n, lam_n, mu_n, params) @ surface.normal - surface.offset_m)[back]
        ok = np.ones(at_scan.size, dtype=bool)
        for half in (slice(0, ALONG_BEAMS), slice(ALONG_BEAMS, 2 * ALONG_BEAMS)):
            n_side = have[:, half].sum(1)
            mean = dist[:, half].sum(1) / np.maximum(n_side, 1)
            ok &= (n_side == 0) | (np.abs(mean - level[id(surface)]) < 0.5 * selection.gate_m)
        return ok

    step = max(1, flat.size // 100_000)
    lam_s, mu_s, r_s = take(np.arange(0, flat.size, step))
    r_s, lam_s, mu_s = true_returns(th, r_s, lam_s, mu_s)
    sample_W = points_W(r_s, lam_s, mu_s, params)
    surfaces = find_surfaces(markers, sensor_W, sample_W)
    level = {id(surface): level_m(surface, sample_W, selection.gate_m) for surface in surfaces}  # from this one sample
    # surface_returns keeps the accepted returns of lowest hash_key: the rows whose key is below a threshold hold
    # them all once they hold max_returns accepted ones, so only those rows are reprojected (the same returns as
    # from every row, at a fraction of the work); the threshold grows until they do, at once to the fraction that
    # the accepted returns so far say is needed (any fraction gives the same returns: the sequence only saves work).
    # Each try judges only the rows above the last one's threshold: the last judged every row below it and
    # accepted fewer than max_returns, all of which stay (their keys are lower than every new row's)
    key = hash_key(scan, beam, seed)
    frac, below = _FRACTIONS[0], 0.0
    parts: list[SurfaceReturns] = []
    while True:
        under = key < np.uint64(frac * (1 << 31)) if frac < 1.0 else None
        if below == 0.0:  # the first try: every key is >= 0
            rows = np.flatnonzero(under) if under is not None else np.arange(key.size)
        else:
            above = key >= np.uint64(below * (1 << 31))
            rows = np.flatnonzero(above & under if under is not None else above)
        lam_k, mu_k, r_k = take(rows)
        r_t, lam_t, mu_t = true_returns(th, r_k, lam_k, mu_k)
        candidates = ReturnRows(scan[rows], beam[rows], lam_k, mu_k, r_k,
                                None if times_at is None else times_at(flat[rows]))
        got = sum(len(p) for p in parts)
        trig = beam_trig(lam_t, mu_t, params.dh)  # once for the points and the candidates' rays (elementwise)
        parts.append(surface_returns(surfaces, points_W_trig(r_t, trig, params), candidates, markers.positions_W,
                                     selection=replace(selection, max_returns=max_returns - got),
                                     rays_W=partial(_rays_of, params, trig),
                                     along=along))
        got += len(parts[-1])
        if got >= max_returns or frac >= 1.0 or not surfaces:  # no surface: no return at any fraction
            return surfaces, _merged(parts, valid.shape[1])
        below, frac = frac, _next_fraction(frac, got, max_returns)


def _rows_of(trig: BeamTrig, i: IntArray) -> BeamTrig:
    """The beams ``i`` (k,) of a :data:`lrfcal.model.kinematics.BeamTrig`."""
    return trig[0][i], trig[1][i], trig[2][i], trig[3][i]


def _rays_of(params: Params, trig: BeamTrig, i: IntArray) -> tuple[FloatArray, FloatArray]:
    """The rays in W (origins, unit directions (k, 3)) of the beams ``i`` (k,) of ``trig``."""
    return beam_rays_W_trig(params, _rows_of(trig, i))


def _merged(parts: list[SurfaceReturns], n_beams: int) -> SurfaceReturns:
    """The returns of :func:`observe_surfaces`' tries as one, in :func:`surface_returns`' order (surface by surface,
    each in the grid's row-major order)."""
    if len(parts) == 1:
        return parts[0]
    def cat(name: str) -> NDArray[Any]:
        return np.concatenate([getattr(p, name) for p in parts])

    scan, beam, surface = cat("scan"), cat("beam"), cat("surface")
    order = np.lexsort((scan * n_beams + beam, surface))  # (surface, flat index): unique pairs
    return SurfaceReturns(
        scan=scan[order], beam=beam[order], lambda_rad=cat("lambda_rad")[order], mu_rad=cat("mu_rad")[order],
        ranges_m=cat("ranges_m")[order], surface=surface[order], normals=cat("normals")[order],
        offsets_m=cat("offsets_m")[order], times_s=None if parts[0].times_s is None else cat("times_s")[order])


#: the fractions of the rows (by hash key) observe_surfaces tries, smallest first: 1/16, then in steps of 1/64, so
#: that the second try reprojects little more than it needs (tunnel_v: 9/64 of the rows, not 1/4)
_FRACTIONS = tuple(k / 64 for k in range(4, 65))
#: the margin on the fraction the accepted returns so far say is needed (they scatter about their expectation)
_FRACTION_MARGIN = 1.25


def _next_fraction(frac: float, n_accepted: int, wanted: int) -> float:
    """The next fraction of rows to try after ``frac`` gave ``n_accepted`` (< ``wanted``) accepted returns: the
    smallest of _FRACTIONS beyond ``frac`` that holds ``wanted`` at the rate seen so far, with a margin (1.0 when
    none was accepted)."""
    need = _FRACTION_MARGIN * frac * wanted / n_accepted if n_accepted > 0 else 1.0
    return next((f for f in _FRACTIONS if f > frac and f >= need), 1.0)


def moved_m(returns: SurfaceReturns, before: tuple[Params, Mapping[str, float]],
            after: tuple[Params, Mapping[str, float]]) -> float:
    """The farthest any of the ``returns`` moved along its surface's normal between two estimates, each its
    parameters and its intrinsics by name (lrfcal.model.unknowns) [m]: the gate of :func:`surface_returns` is on
    that distance."""
    if not len(returns):
        return 0.0

    def along(params: Params, intrinsics: Mapping[str, float]) -> FloatArray:
        r, lam, mu = true_returns(core_vector(params.dh, intrinsics), returns.ranges_m, returns.lambda_rad,
                                  returns.mu_rad)
        return np.einsum("ij,ij->i", points_W(r, lam, mu, params), returns.normals)

    return float(np.max(np.abs(along(*after) - along(*before))))


__all__ += ["level_m", "moved_m", "observe_surfaces"]
