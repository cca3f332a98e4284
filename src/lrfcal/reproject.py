"""Stage 7: reproject every valid return into the motor frame M with a set of DH parameters; PLY export.

Array shapes: S scans, N beams, P cloud points.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .model.kinematics import DH, points_M_trig
from .types import Scans

FloatArray = NDArray[np.float64]


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
    range_offsets_m: Sequence[float] | None = None,
) -> tuple[list[FloatArray], FloatArray]:
    """:func:`reproject_cloud` of the same returns with several DH sets (e.g. nominal and calibrated): the
    valid returns are selected and cos / sin of their motor angles computed once. Returns one (P, 3) cloud per
    DH set (each equal to reproject_cloud's, bit for bit, without range offsets) and the intensity (P,).
    ``range_offsets_m``: one per DH set, subtracted from every range (a calibration's estimated range offset)."""
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
    mk = mu.ravel()[idx] if mu.ndim == 2 else mu[bb]  # (S, N) per-scan bearings (or (N,))
    clouds = []
    offsets = [0.0] * len(dhs) if range_offsets_m is None else list(range_offsets_m)
    for dh, off in zip(dhs, offsets, strict=True):
        phi = dh.beta + mk
        clouds.append(points_M_trig(rk - off if off else rk, cl, sl, np.cos(phi), np.sin(phi), dh))
    intensity = np.ravel(scans.intensities)[idx].astype(np.float64, copy=False)
    return clouds, intensity


#: the header trimesh writes for a vertex-only cloud with an intensity (the format of the files so far, kept byte for
#: byte without importing trimesh, which takes about a second)
_PLY_HEADER = ("ply\nformat binary_little_endian 1.0\ncomment https://github.com/mikedh/trimesh\nelement vertex {n}\n"
               "property float x\nproperty float y\nproperty float z\nproperty float intensity\nelement face 0\n"
               "property list uchar int vertex_indices\nend_header\n")


def write_ply(path: str | Path, points: ArrayLike, intensity: ArrayLike | None = None) -> Path:
    """Write a binary little-endian PLY point cloud (x, y, z float32 and an ``intensity`` float32 property).

    The file is written to a temporary file in the same folder and renamed, so it appears complete or not at all.
    Args:
        points: (P, 3) [m]; intensity: (P,) or None (zeros).
    """
    path = Path(path)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    inten = np.zeros(len(pts)) if intensity is None else np.asarray(intensity, dtype=np.float64).reshape(-1)
    if inten.size != len(pts):
        raise ValueError(f"intensity has {inten.size} values for {len(pts)} points")
    rows = np.empty((len(pts), 4), dtype="<f4")
    rows[:, :3] = pts
    rows[:, 3] = inten
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(_PLY_HEADER.format(n=len(pts)).encode("ascii"))
            f.write(rows.tobytes())
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp makes 0600; give the file the usual mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def current_umask() -> int:
    """The process umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


__all__ = ["current_umask", "reproject_cloud", "reproject_clouds", "write_ply"]
