"""The clouds of a calibration as PLY files (cloud_before.ply, cloud_after.ply: x, y, z and intensity per point,
frame M), written atomically. ``lrfcal reproject``'s richer per-beam PLY is
lrfcal.commands.reproject.write_cloud_ply."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from lrfcal.io.files import write_bytes_atomic

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
    return write_bytes_atomic(path, [_PLY_HEADER.format(n=len(pts)).encode("ascii"), rows.data.cast("B")])


__all__ = ["write_ply"]
