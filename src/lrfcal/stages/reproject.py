"""Stage 7: reproject every valid return into the motor frame M with a set of DH parameters (the clouds' PLY
file: lrfcal.io.ply).

Array shapes: S scans, N beams, P cloud points.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrfcal.model.kinematics import DH, points_M_trig
from lrfcal.model.motor import motor_angles
from lrfcal.model.scanner import true_bearing, true_range
from lrfcal.model.unknowns import SCALE, core_vector
from lrfcal.runtime.forked import on_cores
from lrfcal.types import Scans

FloatArray = NDArray[np.float64]

#: returns above which the DH sets' clouds are reprojected in threads, one per core (lrfcal.runtime.forked.on_cores)
PARALLEL_RETURNS = 100_000
#: returns reprojected at a time: a cloud of millions of returns made in blocks of this many reuses its temporaries
#: (tunnel_v's two clouds in 0.15 s against 0.27-0.37 s in one pass each: the fresh memory's page faults)
CHUNK_RETURNS = 1 << 16


def reproject_cloud(scans: Scans, lambda_rad: ArrayLike, dh: DH, stride: int = 1) -> tuple[FloatArray, FloatArray]:
    """Reproject the valid returns into frame M.

    Args:
        scans: S scans of N beams.
        lambda_rad: (S, N) motor angle of every beam (timing.beam_motor_angles), or (S,) one per scan.
        dh: the DH parameters to use.
        stride: keep every ``stride``-th valid return (in scan-major order) to thin the cloud.
    Returns:
        points_M (P, 3) and intensity (P,) of the kept returns.
    """
    clouds, intensity = reproject_clouds(scans, lambda_rad, (dh,), stride)
    return clouds[0], intensity


def reproject_clouds(
    scans: Scans, lambda_rad: ArrayLike, dhs: Sequence[DH], stride: int = 1,
    intrinsics: Sequence[Mapping[str, float]] | None = None,
) -> tuple[list[FloatArray], FloatArray]:
    """:func:`reproject_cloud` of the same returns with several DH sets (e.g. nominal and calibrated): the
    valid returns are selected and cos / sin of their motor angles computed once. Returns one (P, 3) cloud per
    DH set (each equal to reproject_cloud's, bit for bit, without intrinsics) and the intensity (P,).
    ``intrinsics``: one mapping per DH set of the intrinsics by name (lrfcal.model.unknowns, e.g. a calibration's
    range offset, range scale, motor-angle and bearing scales; those not named at their start), which act on the
    ranges, bearings and motor angles as in the model (lrfcal.model.scanner, lrfcal.model.motor)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    r = scans.ranges_m
    S, N = r.shape
    lam = np.asarray(lambda_rad, dtype=np.float64)
    if lam.shape != r.shape and lam.shape != r.shape[:1]:
        raise ValueError(f"lambda_rad has shape {lam.shape}, expected {r.shape} or {r.shape[:1]}")
    idx = np.flatnonzero(np.isfinite(r))  # scan-major order, as np.nonzero of the (S, N) mask
    if stride > 1:
        idx = idx[::stride]
    bb = idx % N if N else idx
    rk = np.ravel(r)[idx]
    lk = lam.ravel()[idx] if lam.ndim == 2 else lam[idx // N]
    cl, sl = np.cos(lk), np.sin(lk)
    mu = np.asarray(scans.mu_rad, dtype=np.float64)
    row = _shared_bearings(mu)  # (N,) when every scan has the same bearings (a fixed scanner), else None
    mk = None if row is not None else mu.ravel()[idx] if mu.ndim == 2 else mu[bb]  # (S, N) per-scan bearings
    cores = [core_vector(dh, {} if intrinsics is None else intrinsics[i]) for i, dh in enumerate(dhs)]

    def cloud(dh: DH, th: FloatArray) -> FloatArray:
        out = np.empty((rk.size, 3))
        if row is not None:  # cos and sin of each beam's phi once, gathered: elementwise, the same bits
            phi_beam = dh.beta + true_bearing(th, row).mu
            cos_beam, sin_beam = np.cos(phi_beam), np.sin(phi_beam)
        for s in range(0, rk.size, CHUNK_RETURNS):  # elementwise: the same bits, the temporaries reused in cache
            e = min(rk.size, s + CHUNK_RETURNS)
            if mk is not None:
                phi = dh.beta + true_bearing(th, mk[s:e]).mu
                cp, sp = np.cos(phi), np.sin(phi)
            else:
                cp, sp = cos_beam[bb[s:e]], sin_beam[bb[s:e]]
            if th[SCALE] == 1.0:
                c, sn = cl[s:e], sl[s:e]
            else:
                lam_true = motor_angles(th, lk[s:e], None, None).lam
                c, sn = np.cos(lam_true), np.sin(lam_true)
            out[s:e] = points_M_trig(true_range(th, rk[s:e], on_marker=False).r, c, sn, cp, sp, dh)
        return out

    clouds = on_cores(cloud, list(zip(dhs, cores, strict=True)), parallel=rk.size > PARALLEL_RETURNS)
    intensity = np.ravel(scans.intensities)[idx].astype(np.float64, copy=False)
    return clouds, intensity


def _shared_bearings(mu: FloatArray) -> FloatArray | None:
    """The bearings (N,) every scan shares, bit for bit, when ``mu`` (S, N) holds one row for all scans (or is (N,)),
    else None."""
    if mu.ndim == 1:
        return mu
    bits = np.ascontiguousarray(mu).view(np.int64)  # the same bits, not only equal values (-0.0 and 0.0 differ)
    if mu.shape[0] and bool((bits == bits[0]).all()):
        return mu[0]
    return None


__all__ = ["reproject_cloud", "reproject_clouds"]
