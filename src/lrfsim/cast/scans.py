"""The ray cast of lrfsim.sensors.lidar: the rays of every beam's sub-rays in batches, cast with ``mujoco.mj_multiRay``
on both cores, and the mixed-pixel model (poses, batching and mixture: lrfsim.sensors.lidar's module docstring).

Threads. ``mj_multiRay`` releases the GIL (mujoco's python bindings; measured with mujoco 4.0.0: two threads cast
1.7x as many rays per second as one on a 2-core machine already busy), so chunks of scans are cast in a thread pool,
each thread with its own ``MjData`` (the kinematics of a chunk's scans and the ray buffers are per thread; the scene's
geoms that the lidar sees are static, so every copy casts against the same world). Every chunk is computed by the
same arithmetic whichever thread runs it, and writes only its own scans: the recording is byte-identical with any
number of threads (tests/test_lidar.py). ``progress(done_scans, total_scans)`` is called from the calling thread,
chunk by chunk in scan order. The rays of a chunk and their casts: lrfsim.cast.chunks; by default
(``sensor.footprint_cast: edges``) the footprint's ring is cast only where it can change a beam.
"""

from __future__ import annotations

import copy
import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrfcal import cores, one_blas_thread
from lrfcal.errors import InputError
from lrfsim.scenario.sections import SensorConfig
from lrfsim.sensors.lidar import (
    _MIN_NORMAL_DOT,
    RETRO_EXPONENT,
    Cast,
    LidarOutput,
    SceneLike,
    ring_half_angle,
    sensor_model,
    split_echoes,
)

from .chunks import RayChunk, _RayMaker, cast_chunk, cast_chunk_edges, cast_cutoff_m, iter_ray_chunks, plan_runs
from .forked import Forked, can_fork, run_forked, shared_empty

FloatArray = NDArray[np.float64]

#: scans per chunk: one task of the thread pool
CHUNK_SCANS = 16


def default_threads() -> int:
    """Threads of the cast: the cores this process may use, at most 4 (``LRFSIM_CAST_THREADS`` overrides)."""
    env = os.environ.get("LRFSIM_CAST_THREADS", "").strip()
    if env.isdigit() and int(env) >= 1:
        return int(env)
    return max(1, min(4, cores()))


def simulate_scans(scene: SceneLike, sensor: SensorConfig, beam_lambda_rad: FloatArray,
                   rng: np.random.Generator, *, origin_tol_m: float = 1e-6, chunk_scans: int = CHUNK_SCANS,
                   progress: Callable[[int, int], None] | None = None,
                   beam_times_s: FloatArray | None = None) -> LidarOutput:
    """Ray cast and sensor model (module docstring) for motor angles ``beam_lambda_rad`` (S, N) at every beam:
    ``sensor_model(cast_scans(...), sensor, rng, beam_times_s)``.

    ``rng`` draws the range and intensity noise (all of it up front, so results do not depend on the
    chunking; the echoes' extra draws come after). ``progress(done_scans, total_scans)`` is called after every
    chunk. ``beam_times_s`` (S, N): true beam times [s], needed only by the warm-up drift.
    """
    cast = cast_scans(scene, sensor, beam_lambda_rad, origin_tol_m=origin_tol_m, chunk_scans=chunk_scans,
                      progress=progress)
    return sensor_model(cast, sensor, rng, beam_times_s)


@dataclass
class _Workspace:
    """One thread's MjData and buffers for a chunk of scans."""

    data: Any
    dirs: FloatArray  # (chunk, N, F, 3)
    B0: FloatArray  # (chunk, N, 3, 3)
    gid: NDArray[np.int32]  # (chunk N F,)
    dist: FloatArray  # (chunk N F,)
    nrm: FloatArray  # (chunk N F, 3)


@dataclass(frozen=True)
class _ChunkStats:
    n_rays: int
    n_calls: int
    cast_s: float
    max_off: float
    max_corr: float


@dataclass(frozen=True)
class _Mixture:
    """What the mixed-pixel model needs besides a chunk's hits, and the arrays it writes the beams into: ranges and
    intensities (S, N); with echoes, their ranges and powers (S, N, max_echoes), else None."""

    sensor: SensorConfig
    reflectivity: FloatArray  # (ngeom,)
    is_marker: NDArray[np.bool_]  # (ngeom,)
    ranges: FloatArray
    intensities: FloatArray
    echo_ranges: FloatArray | None
    echo_power: FloatArray | None

    def write(self, ch: RayChunk, gid: NDArray[np.int32], dist: FloatArray, normal: FloatArray,
              dn: FloatArray | None = None) -> tuple[float, float]:
        """The beams of a cast chunk (hits gid, dist (Sc N F,), normal (Sc N F, 3)) into the chunk's scans: each
        sub-ray's range corrected from the call's shared origin to the beam's own (parallax), its received power
        (Lambertian, retroreflector lobe for markers, inverse square), the incidence bias, then the power-weighted
        range and the mean power; echoes split by range. ``dn`` (Sc, N, F): each sub-ray's direction dotted with
        its normal, when the chunk holds the centre rays only (:func:`cast_chunk_edges`). Returns (largest origin
        offset, largest parallax correction) [m]."""
        cfg, F = self.sensor.intensity, self.sensor.footprint_rays
        Sc, N = ch.offset.shape[:2]
        g = gid.reshape(Sc, N, F)
        hit = g >= 0
        nv = normal.reshape(Sc, N, F, 3)
        if dn is None:
            dn = np.einsum("sbfk,sbfk->sbf", ch.directions.reshape(Sc, N, F, 3), nv)
        en = np.einsum("sbk,sbfk->sbf", ch.offset, nv)
        ok = hit & (np.abs(dn) > _MIN_NORMAL_DOT)
        corr = np.divide(en, dn, out=np.zeros_like(dn), where=ok)
        r = np.where(hit, dist.reshape(Sc, N, F) + corr, 1.0)
        max_off = float(np.sqrt(np.max(np.einsum("sbk,sbk->sb", ch.offset, ch.offset))))
        max_corr = float(np.max(np.abs(corr)))
        gi = np.where(hit, g, 0)
        cos = np.minimum(np.abs(dn), 1.0)
        lobe = cos
        mk = self.is_marker[gi] & hit
        if mk.any():
            lobe = cos.copy()
            lobe[mk] = cos[mk] ** RETRO_EXPONENT
        P = cfg.gain_counts * self.reflectivity[gi] * lobe * (cfg.ref_range_m / np.maximum(r, 1e-9)) ** 2
        P *= hit
        k_theta = self.sensor.systematic.incidence_bias_m
        if k_theta != 0.0:  # incidence bias per sub-ray; the received power keeps the true range
            r = r + k_theta * np.arccos(cos)
        Psum = P.sum(-1)
        PR = np.einsum("sbf,sbf->sb", P, r)
        sl = ch.scans
        self.ranges[sl] = np.divide(PR, Psum, out=np.full_like(PR, np.nan), where=Psum > 0)
        self.intensities[sl] = Psum / F
        if self.echo_ranges is not None and self.echo_power is not None:
            ech = self.sensor.echoes
            re, pe, single = split_echoes(r, P, hit, ech.separation_m, ech.max_echoes)
            re[single, 0] = self.ranges[sl][single]
            pe[single, 0] = Psum[single]
            self.echo_ranges[sl] = re
            self.echo_power[sl] = pe
        return max_off, max_corr


def _local_empty(shape: tuple[int, ...], fill: float | None = None) -> FloatArray:
    """np.empty, or np.full with ``fill`` (lrfsim.cast.forked.shared_empty's signature)."""
    return np.empty(shape) if fill is None else np.full(shape, fill)


def _run_chunks(run: Callable[[int], _ChunkStats], S: int, chunk_scans: int, n_threads: int | Forked,
                progress: Callable[[int, int], None] | None) -> list[_ChunkStats]:
    """``run(s0)`` for every chunk of scans [s0, s0 + chunk_scans), in ``n_threads`` threads (or shared with a
    forked helper process, lrfsim.cast.forked, ``progress`` then called once all are cast); the chunks' stats in scan
    order, ``progress(done_scans, S)`` after each."""
    starts = range(0, S, chunk_scans)
    stats: list[_ChunkStats] = []
    if isinstance(n_threads, Forked):
        with one_blas_thread():
            forked = run_forked(lambda i: run(starts[i]), len(starts), n_threads.meanwhile)
        n_threads = 1
        run = dict(zip(starts, forked, strict=True)).__getitem__  # collected below, with progress, in scan order

    def collect(results: Iterator[_ChunkStats]) -> None:
        for s0, st in zip(starts, results, strict=True):
            stats.append(st)
            if progress is not None:
                progress(min(S, s0 + chunk_scans), S)

    if n_threads == 1:
        collect(map(run, starts))
    else:
        # the chunks are the cast's parallelism: no BLAS threads inside their matrix products (lrfsim.cast.chunks)
        with one_blas_thread(), ThreadPoolExecutor(max_workers=n_threads, thread_name_prefix="lrfsim-cast") as pool:
            collect(pool.map(run, starts))
    return stats


def cast_scans(scene: SceneLike, sensor: SensorConfig, beam_lambda_rad: FloatArray, *, origin_tol_m: float = 1e-6,
               chunk_scans: int = CHUNK_SCANS, progress: Callable[[int, int], None] | None = None,
               threads: int | Forked | None = None, footprint: str | None = None) -> Cast:
    """The ray cast and the mixed-pixel model (lrfsim.sensors.lidar's module docstring), without the sensor model;
    beam_lambda_rad (S, N).

    ``footprint`` (default: ``sensor.footprint_cast``): "full" casts every sub-ray of every beam; "edges" casts the
    footprint's ring only where it can change a beam (:func:`cast_chunk_edges`: at edges and near markers), elsewhere
    each sub-ray takes the centre ray's tangent plane: about a fifth of the rays, with the ranges of "full" to
    rounding on planes (a ring wider than the angle between beams: "full").

    The cast reaches range_max + 5 sigma of the largest noise band when ``sensor.noise`` is set (a return just
    beyond range_max can be pulled back by the noise), else range_max. ``threads``: chunks of ``chunk_scans`` scans
    cast in that many threads (default :func:`default_threads`), or a :class:`lrfsim.cast.forked.Forked`: shared with a
    forked helper process, where it can be forked (for casts of many short calls; the result does not depend on it);
    ``progress(done_scans, total_scans)`` after every chunk, in scan order. Cast.cast_time_s sums the chunks' time
    inside ``mj_multiRay`` over the threads.
    """
    t_start = time.perf_counter()
    lam = np.ascontiguousarray(beam_lambda_rad, dtype=float)
    if lam.ndim != 2 or lam.shape[1] != sensor.n_beams:
        raise InputError(f"lidar: beam_lambda_rad must have shape (S, {sensor.n_beams}), got {lam.shape}")
    S, N = lam.shape
    F = sensor.footprint_rays
    footprint = sensor.footprint_cast if footprint is None else footprint
    geomgroup = np.ascontiguousarray(scene.lidar_geomgroup, dtype=np.uint8)
    cutoff = cast_cutoff_m(sensor)
    E = sensor.echoes.max_echoes
    echoes = sensor.echoes.enabled
    forked = isinstance(threads, Forked) and can_fork(-(-S // chunk_scans))
    empty = shared_empty if forked else _local_empty
    mix = _Mixture(sensor, np.asarray(scene.geom_reflectivity, dtype=float),
                   np.asarray(scene.geom_is_marker, dtype=bool), empty((S, N)), empty((S, N)),
                   empty((S, N, E), np.nan) if echoes else None, empty((S, N, E), 0.0) if echoes else None)
    if isinstance(threads, Forked) and not forked:  # no helper: cast here (after ``meanwhile``), in threads
        if threads.meanwhile is not None:
            threads.meanwhile()
        threads = None
    if S == 0:
        return Cast(ranges_m=mix.ranges, intensities=mix.intensities, n_rays=0, n_calls=0, cast_time_s=0.0,
                    total_time_s=time.perf_counter() - t_start, max_origin_error_m=0.0, max_parallax_correction_m=0.0,
                    cutoff_m=cutoff, echo_ranges_m=mix.echo_ranges, echo_power=mix.echo_power)
    if footprint not in ("full", "edges"):
        raise InputError(f"lidar: footprint must be 'full' or 'edges', got {footprint!r}")
    maker = _RayMaker(scene, sensor, lam, origin_tol_m)  # (its kinematics placed scene.data's geoms)
    # the edge test compares a beam with its neighbours: it sees every edge the ring can reach while the ring's
    # diameter is within the angle between neighbouring beams (else every sub-ray is cast)
    edges = footprint == "edges" and F > 1 and 2.0 * ring_half_angle(sensor) < abs(sensor.angle_increment_rad)
    mk = np.flatnonzero(np.asarray(scene.geom_is_marker, dtype=bool))
    markers = (scene.data.geom_xpos[mk].copy(), scene.model.geom_rbound[mk].copy(), ring_half_angle(sensor))
    n_threads: int | Forked = threads if isinstance(threads, Forked) else max(
        1, min(default_threads() if threads is None else int(threads), -(-S // chunk_scans)))
    local = threading.local()
    halo = 1 if edges else 0  # "edges" compares a chunk's first and last scans with their neighbours outside it
    M = chunk_scans * N * F  # the full cast's hits (the edges' are cast_chunk_edges' own)

    def workspace() -> _Workspace:
        ws = getattr(local, "ws", None)
        if ws is None:
            # a thread's own MjData (a forked helper has its own copy of scene.data)
            data = scene.data if not isinstance(n_threads, int) or n_threads == 1 else copy.copy(scene.data)
            ws = local.ws = _Workspace(data, np.empty((chunk_scans, N, F, 3)),
                                       np.empty((chunk_scans + 2 * halo, N, 3, 3)),
                                       np.empty(M, dtype=np.int32), np.empty(M), np.empty((M, 3)))
        return ws

    def run(s0: int) -> _ChunkStats:
        ws = workspace()
        s1 = min(S, s0 + chunk_scans)
        h0, h1 = max(0, s0 - halo), min(S, s1 + halo)
        ch = maker.chunk(h0, h1, ws.data, ws.dirs, ws.B0, centre_only=edges)
        t0 = time.perf_counter()
        dn = None
        if edges:
            k0, k1 = s0 - h0, s1 - h0
            gid, dist, nrm, dn, m = cast_chunk_edges(scene.model, ws.data, geomgroup, ch, cutoff, maker.coef, markers,
                                                     (k0, k1))
            ch = ch.inner(k0, k1)
        else:
            m = (h1 - h0) * N * F
            gid, dist, nrm = ws.gid[:m], ws.dist[:m], ws.nrm[:m]
            cast_chunk(scene.model, ws.data, geomgroup, ch, cutoff, gid, dist, nrm)
        cast_s = time.perf_counter() - t0
        max_off, max_corr = mix.write(ch, gid, dist, nrm, dn)
        return _ChunkStats(m, len(ch.call_first), cast_s, max_off, max_corr)

    stats = _run_chunks(run, S, chunk_scans, n_threads, progress)
    return Cast(ranges_m=mix.ranges, intensities=mix.intensities, n_rays=sum(s.n_rays for s in stats),
                n_calls=sum(s.n_calls for s in stats), cast_time_s=sum(s.cast_s for s in stats),
                total_time_s=time.perf_counter() - t_start, max_origin_error_m=max(s.max_off for s in stats),
                max_parallax_correction_m=max(s.max_corr for s in stats), cutoff_m=cutoff,
                echo_ranges_m=mix.echo_ranges, echo_power=mix.echo_power)


__all__ = ["CHUNK_SCANS", "RayChunk", "cast_chunk", "cast_chunk_edges", "cast_cutoff_m", "cast_scans",
           "default_threads", "iter_ray_chunks", "plan_runs", "simulate_scans"]
