"""The rays of a chunk of scans and their casts with ``mujoco.mj_multiRay`` (the poses and the batching of
lrfsim.sensors.lidar's module docstring): every sub-ray of every beam (:func:`cast_chunk`, the simulator's cast), or the
footprint's ring only where it can change a beam (:func:`cast_chunk_edges`, `lrfsim plan`'s noise-free cast). The
thread pool and the mixed-pixel model that use them: lrfsim.cast.scans.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfsim.scenario.sections import SensorConfig
from lrfsim.sensors.lidar import _MIN_NORMAL_DOT, SceneLike, _skew, beam_angles, footprint_coefficients, site_poses_W

FloatArray = NDArray[np.float64]


@dataclass
class RayChunk:
    """The rays of a chunk of Sc scans, in the order they are cast (views into reused buffers).

    directions (Sc*N*F, 3) unit sub-ray directions; call_origins (C, 3) one origin per mj_multiRay call;
    call_first (C,) first ray, call_count (C,) number of rays of each call; offset (Sc, N, 3) = shared origin
    minus the beam's exact origin; scans: slice of the chunk's scans in the recording.
    """

    directions: FloatArray
    call_origins: FloatArray
    call_first: list[int]
    call_count: list[int]
    offset: FloatArray
    scans: slice
    frames: FloatArray | None = None  # (Sc, N, 3, 3) each beam's frame B (columns e, t, z in W): centre-only chunks

    def inner(self, k0: int, k1: int) -> RayChunk:
        """The chunk's scans [k0, k1) (counted from its first) as a chunk of their own (runs never cross scans)."""
        Sc, N = self.offset.shape[:2]
        per_scan = self.directions.shape[0] // Sc
        lo, hi = k0 * per_scan, k1 * per_scan
        keep = [i for i, a in enumerate(self.call_first) if lo <= a < hi]
        return RayChunk(self.directions[lo:hi], self.call_origins[keep], [self.call_first[i] - lo for i in keep],
                        [self.call_count[i] for i in keep], self.offset[k0:k1],
                        slice(self.scans.start + k0, self.scans.start + k1),
                        None if self.frames is None else self.frames[k0:k1])


def plan_runs(origins: FloatArray, tol_m: float) -> int:
    """Run length n for one scan's exact beam origins (N, 3): the largest odd n with (n-1)/2 * step < tol."""
    return _run_lengths(origins[None], tol_m)[0]


def _run_lengths(origins: FloatArray, tol_m: float) -> list[int]:
    """:func:`plan_runs` of every scan of ``origins`` (Sc, N, 3) at once."""
    Sc, N = origins.shape[:2]
    steps = np.linalg.norm(np.diff(origins, axis=1), axis=2).max(axis=1) if N > 1 else np.zeros(Sc)
    return [N if step == 0.0 else max(1, min(N, 2 * int(math.floor(tol_m / step * (1.0 - 1e-12))) + 1))
            for step in steps.tolist()]


class _RayMaker:
    """The rays of one chunk of scans (:func:`iter_ray_chunks`), with what all chunks share computed once."""

    def __init__(self, scene: SceneLike, sensor: SensorConfig, beam_lambda_rad: FloatArray, origin_tol_m: float):
        self.scene, self.lam, self.tol = scene, beam_lambda_rad, origin_tol_m
        N = beam_lambda_rad.shape[1]
        mu = beam_angles(sensor)
        self.cmu, self.smu = np.cos(mu)[None, :, None], np.sin(mu)[None, :, None]
        self.coef = footprint_coefficients(sensor)
        self.coef_T = np.ascontiguousarray(self.coef.T)
        self.F = sensor.footprint_rays
        self.ar = np.arange(N)
        u = site_poses_W(scene, beam_lambda_rad[:1, N // 2])[3]  # the hinge's axis, as the first chunk sees it
        self.K = _skew(u)
        self.K2 = self.K @ self.K

    def chunk(self, s0: int, s1: int, data: Any, dirs_buf: FloatArray, B0: FloatArray, centre_only: bool = False
              ) -> RayChunk:
        """Scans [s0, s1), their directions written into dirs_buf (>= s1 - s0, N, F, 3), kinematics in ``data``;
        ``centre_only``: the centre rays alone (one per beam, the same numbers as the full chunk's first sub-ray)
        and the beams' frames."""
        N, F, ar = self.ar.size, (1 if centre_only else self.F), self.ar
        Sc = s1 - s0
        lam = self.lam[s0:s1]
        ref = lam[:, N // 2]
        p, R, a, _ = site_poses_W(self.scene, ref, data)
        delta = lam - ref[:, None]  # (Sc, N)
        Rot = np.sin(delta)[..., None, None] * self.K + (1.0 - np.cos(delta))[..., None, None] * self.K2
        Rot += np.eye(3)
        origins = a + np.einsum("sbij,sj->sbi", Rot, p - a, optimize=True)  # (Sc, N, 3)
        X, Y, Z = R[:, None, :, 0], R[:, None, :, 1], R[:, None, :, 2]  # (Sc, 1, 3)
        b0 = B0[:Sc]
        b0[..., 0] = self.cmu * X + self.smu * Y
        b0[..., 1] = self.cmu * Y - self.smu * X
        b0[..., 2] = Z
        B = np.matmul(Rot, b0)
        if centre_only:  # the footprint's row 0 is (1, 0, 0): the centre ray is B's first column, exactly
            dirs = np.ascontiguousarray(B[..., 0])
        else:  # sub-ray f = B coef_f: one matrix product over every beam's rows (a third faster than a batched one)
            dirs = dirs_buf[:Sc]
            dirs[...] = (B.reshape(-1, 3) @ self.coef_T).reshape(Sc, N, 3, F).transpose(0, 1, 3, 2)
        # runs of beams sharing one origin
        offset = np.empty((Sc, N, 3))
        call_origins: list[FloatArray] = []
        first: list[int] = []
        count: list[int] = []
        for k, n in enumerate(_run_lengths(origins, self.tol)):
            starts = np.arange(0, N, n)
            stops = np.minimum(starts + n, N)
            mids = (starts + stops - 1) // 2
            call_origins.append(origins[k, mids])
            first.extend((k * N * F + starts * F).tolist())
            count.extend(((stops - starts) * F).tolist())
            offset[k] = origins[k, mids[ar // n]] - origins[k]
        return RayChunk(directions=dirs.reshape(Sc * N * F, 3), call_origins=np.concatenate(call_origins),
                        call_first=first, call_count=count, offset=offset, scans=slice(s0, s1),
                        frames=B if centre_only else None)


def iter_ray_chunks(scene: SceneLike, sensor: SensorConfig, beam_lambda_rad: FloatArray, *,
                    origin_tol_m: float = 1e-6, chunk_scans: int = 16) -> Iterator[RayChunk]:
    """Generate the rays of all scans, chunk by chunk (the module docstring's poses and batching).

    ``beam_lambda_rad`` (S, N): the true motor angle at every beam's time. Per beam, the hinge rotation
    Rot(u, d) = I + sin(d) K + (1 - cos(d)) K^2 (K = [u]x) gives the beam frame B = Rot R_s Rz(mu) (columns
    e, t, z in W) and the origin a + Rot (p_s - a); sub-ray directions are B times
    :func:`footprint_coefficients`. The yielded arrays are reused between chunks: copy them to keep them.
    """
    S, N = beam_lambda_rad.shape
    maker = _RayMaker(scene, sensor, beam_lambda_rad, origin_tol_m)
    dirs_buf = np.empty((chunk_scans, N, sensor.footprint_rays, 3))
    B0 = np.empty((chunk_scans, N, 3, 3))
    for s0 in range(0, S, chunk_scans):
        yield maker.chunk(s0, min(S, s0 + chunk_scans), scene.data, dirs_buf, B0)


def cast_cutoff_m(sensor: SensorConfig) -> float:
    """How far a ray is cast [m]: the longest range plus 5 sigma of the widest noise band or of the range-proportional
    noise at the longest range (and 1 mm)."""
    sig_max = max((b.sigma_m for b in sensor.noise_bands), default=0.0)
    sig_max = max(sig_max, sensor.noise_range_fraction * sensor.range_max_m)
    return sensor.range_max_m + (5.0 * sig_max if sensor.noise else 0.0) + 1e-3


def cast_chunk(model: Any, data: Any, geomgroup: NDArray[np.uint8], chunk: RayChunk, cutoff_m: float,
               geomid: NDArray[np.int32], dist: FloatArray, normal: FloatArray) -> None:
    """Cast every call of a chunk with ``mujoco.mj_multiRay`` into geomid (M,), dist (M,), normal (M, 3)."""
    import mujoco

    multi_ray = mujoco.mj_multiRay
    dflat = chunk.directions.reshape(-1)
    nflat = normal.reshape(-1)
    for o, a, n in zip(chunk.call_origins, chunk.call_first, chunk.call_count, strict=True):
        b = a + n
        multi_ray(model, data, o, dflat[3 * a:3 * b], geomgroup, 1, -1, geomid[a:b], dist[a:b],
                  nflat[3 * a:3 * b], n, cutoff_m)


#: ``footprint="edges"``: neighbours whose centre-ray normals differ by more than this angle mark an edge [rad]
EDGE_NORMAL_RAD = math.radians(1.0)


def _edge_beams(gid: NDArray[np.int32], normal: FloatArray) -> NDArray[np.bool_]:
    """(Sc, N) the beams whose centre ray hit (gid (Sc, N), normal (Sc, N, 3)) differs from one of its 8 neighbours'
    (the beams beside it in its scan and the next and previous scans of the chunk: an edge that runs diagonally
    through the grid of beams passes between a beam and a diagonal neighbour): another geom, a miss beside a hit, or
    a normal turned by more than :data:`EDGE_NORMAL_RAD` (a box's other face, a curved geom)."""
    cos_lim = math.cos(EDGE_NORMAL_RAD)
    S, N = gid.shape
    edge = np.zeros(gid.shape, dtype=bool)
    for ds, db in ((1, 0), (0, 1), (1, 1), (1, -1)):
        a = (slice(0, S - ds), slice(max(0, -db), N - max(0, db)))  # a beam ...
        b = (slice(ds, S), slice(max(0, db), N - max(0, -db)))  # ... and its neighbour (ds, db) further on
        turned = np.einsum("...k,...k->...", normal[a], normal[b]) < cos_lim
        differ = (gid[a] != gid[b]) | (turned & (gid[a] >= 0))  # a miss's normal means nothing
        edge[a] |= differ
        edge[b] |= differ
    return edge


def _near_markers(origins: FloatArray, dirs: FloatArray, centres: FloatArray, radii: FloatArray,
                  half_angle: float) -> NDArray[np.bool_]:
    """(B,) the centre rays (origins, unit dirs (B, 3)) that pass within a marker geom's bounding sphere (centres
    (m, 3), radii (m,)) widened by the footprint's ring at that distance and 1 mm."""
    od = np.einsum("bk,bk->b", origins, dirs)
    t = dirs @ centres.T - od[:, None]  # (B, m) along the ray to the closest approach
    v2 = (np.einsum("mk,mk->m", centres, centres)[None, :] - 2.0 * (origins @ centres.T)
          + np.einsum("bk,bk->b", origins, origins)[:, None])
    reach = radii[None, :] + np.abs(t) * 2.0 * half_angle + 1e-3
    return np.any(v2 - t * t < reach * reach, axis=1)


def _markers_near_scans(origins: FloatArray, frames: FloatArray, markers: tuple[FloatArray, FloatArray, float]
                        ) -> NDArray[np.bool_]:
    """(m,) the markers (centres (m, 3), bounding radii (m,), the ring's half angle) that some beam of these scans
    (origins (Si, N, 3), frames (Si, N, 3, 3)) can pass near: within reach of the scan plane (normal: the frame's z)
    at the scan's first, middle or last beam, or on both sides of it (the plane turns smoothly within a scan)."""
    centres, radii, half = markers
    if not len(centres):
        return np.zeros(0, dtype=bool)
    N = origins.shape[1]
    pick = [0, N // 2, N - 1]
    z, o = frames[:, pick][..., 2], origins[:, pick]  # (Si, 3, 3)
    side = np.einsum("spk,mk->spm", z, centres) - np.einsum("spk,spk->sp", z, o)[..., None]  # (Si, 3, m)
    far = np.linalg.norm(centres[None, None] - o[:, :, None], axis=-1)
    reach = radii + far * 2.0 * half + 2e-3
    close = (np.abs(side) < reach).any(axis=1) | (np.ptp(np.sign(side), axis=1) > 0)
    return close.any(axis=0)


def cast_chunk_edges(model: Any, data: Any, geomgroup: NDArray[np.uint8], chunk: RayChunk, cutoff_m: float,
                     coef: FloatArray, markers: tuple[FloatArray, FloatArray, float], inner: tuple[int, int]
                     ) -> tuple[NDArray[np.int32], FloatArray, FloatArray, FloatArray, int]:
    """The footprint's ring cast only where it can matter (``cast_scans(..., footprint="edges")``), for a
    centre-only chunk (``_RayMaker.chunk(..., centre_only=True)``) and the footprint's sub-ray coefficients
    coef (F, 3).

    Every beam's centre ray is cast; the ring's F - 1 sub-rays are cast for the beams at an edge
    (:func:`_edge_beams`; a scan's first and last beams and the recording's first and last scans too) or near a
    marker (``markers``: centres (m, 3), bounding radii (m,) and the ring's half
    angle; :func:`_near_markers`), among the chunk's scans ``inner`` [k0, k1) (the others, one on each side, are
    cast for their centre rays only: the neighbours of the inner scans at the chunk's borders). Elsewhere the ring's
    sub-rays meet the centre ray's tangent plane (geom, normal, and the distance along their own direction): exact on
    a plane, and within r rho^2 of the full cast on a curved geom whose normal turns by less than
    :data:`EDGE_NORMAL_RAD` between neighbours (rho the ring's half angle). What the neighbours cannot see: a feature
    thinner than the beam spacing that only the ring touches (a plane's edge at grazing incidence, a box's corner,
    while the servo stands still). Measured against the full cast (noise-free, the shipped scenarios): 0 (tunnel_v,
    spinning_tilted), 6 (room_box) and 62 (plane_30deg) of 1.6 million beams differ; plan's sigmas agree to 3e-13.

    Returns the inner scans' sub-ray hits as :meth:`_Mixture.write` takes them: geomid, distance (Si N F,),
    normals (Si N F, 3), n . d (Si, N, F), and the number of rays cast.
    """
    import mujoco

    multi_ray = mujoco.mj_multiRay
    assert chunk.frames is not None
    Sc, N = chunk.offset.shape[:2]
    F = coef.shape[0]
    g0, t0, n0 = np.empty(Sc * N, dtype=np.int32), np.empty(Sc * N), np.empty((Sc * N, 3))
    cast_chunk(model, data, geomgroup, chunk, cutoff_m, g0, t0, n0)  # the centre rays: one per beam
    call_of = np.repeat(np.arange(len(chunk.call_count)), chunk.call_count)  # the calls cover the beams in order
    k0, k1 = inner
    lo, hi = k0 * N, k1 * N
    ring = _edge_beams(g0.reshape(Sc, N), n0.reshape(Sc, N, 3))
    ring[:, [0, -1]] = True  # a scan's first and last beams, and the recording's first and last scans: a neighbour
    ring[[0, -1]] = True  # is missing (in the chunk's scans, the first and last are halo unless the recording's own)
    ring = ring[k0:k1].ravel()
    origins = chunk.call_origins[call_of[lo:hi]]
    near = _markers_near_scans(origins.reshape(k1 - k0, N, 3), chunk.frames[k0:k1], markers)
    if near.any():
        centres, radii, half = markers
        ring |= _near_markers(origins, chunk.directions[lo:hi], centres[near], radii[near], half)
    B = chunk.frames[k0:k1].reshape(-1, 3, 3)
    g0, t0, n0, call_of = g0[lo:hi], t0[lo:hi], n0[lo:hi], call_of[lo:hi]
    # each sub-ray meets the centre ray's tangent plane: n . d_f = (B^T n) . coef_f, t_f = t_0 (n . d_0) / (n . d_f)
    dn = np.einsum("bjk,bj->bk", B, n0) @ coef.T  # (Si N, F)
    g = np.repeat(g0[:, None], F, axis=1)
    nv = np.repeat(n0[:, None, :], F, axis=1)
    ok = (g0[:, None] >= 0) & (np.abs(dn) > _MIN_NORMAL_DOT)
    t = np.repeat(t0[:, None], F, axis=1)
    np.divide(t0[:, None] * dn[:, :1], dn, out=t, where=ok)
    # the marked beams in blocks of consecutive beams of one call, every sub-ray of a block cast in one call
    step = np.diff(np.concatenate([[0], ring.astype(np.int8), [0]]))
    new_call = np.zeros(ring.size + 1, dtype=bool)
    new_call[1:-1] = call_of[1:] != call_of[:-1]
    starts = np.flatnonzero((step[:-1] == 1) | (ring & new_call[:-1]))
    stops = np.flatnonzero((step[1:] == -1) | (ring & new_call[1:])) + 1
    # the blocks cover the marked beams in order: their sub-rays computed, and their hits placed, all at once (the
    # same numbers as block by block; only the calls go one by one)
    marked = np.flatnonzero(ring)
    dirs = np.matmul(coef, np.swapaxes(B[marked], -1, -2))  # (nr, F, 3): the full chunk's numbers
    gb, tb, nvb = np.empty((marked.size, F), dtype=np.int32), np.empty((marked.size, F)), np.empty((marked.size, F, 3))
    d_all, g_all, t_all, n_all = dirs.reshape(-1), gb.reshape(-1), tb.reshape(-1), nvb.reshape(-1)
    a = 0  # the block's first sub-ray among the marked beams'
    for b0, nb in zip(starts.tolist(), (stops - starts).tolist(), strict=True):
        b = a + nb * F
        multi_ray(model, data, chunk.call_origins[call_of[b0]], d_all[3 * a:3 * b], geomgroup, 1, -1, g_all[a:b],
                  t_all[a:b], n_all[3 * a:3 * b], nb * F, cutoff_m)
        a = b
    g[marked], t[marked], nv[marked] = gb, tb, nvb
    dn[marked] = np.einsum("bfk,bfk->bf", dirs, nvb)
    return (g.reshape(-1), t.reshape(-1), nv.reshape(-1, 3), dn.reshape(k1 - k0, N, F),
            Sc * N + int(ring.sum()) * F)


__all__ = ["EDGE_NORMAL_RAD", "RayChunk", "cast_chunk", "cast_chunk_edges", "cast_cutoff_m", "iter_ray_chunks",
           "plan_runs"]
