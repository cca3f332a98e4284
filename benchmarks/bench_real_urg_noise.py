"""The real URG-04LX stand's range noise by range and its wiggle along the scan (issue 54: what the replicas
scenarios/urg_box_60.yaml and urg_room_90.yaml copy; docs/real-data.md).

Reads the public recordings of github.com/liangfok/tilting_lidar_scanner (bags/cardboard_box.bag and room_240.bag at
commit 438ea81) from ../shared/realbags/ beside the clone (not part of the project; skipped when absent):
  - the range noise by range band: the second difference over scans of each beam's range, r(k+1) - 2 r(k) + r(k-1),
    cancels the scene's slow change while the stand steps 0.075 deg a scan; its robust scale (1.4826 MAD) / sqrt(6)
    is the noise (docs/real-data.md, "The range noise of a real URG-04LX");
  - the wiggle along the scan on the box: the facing wall's returns, reprojected with the authors' nominal DH, less a
    quadratic surface fitted to them, averaged per beam over the scans; the correlation of that per-beam pattern
    between quarters of the recording (the same tilts: the way up and the way back; other tilts) and its strongest
    period and amplitude.

    python benchmarks/bench_real_urg_noise.py
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from lrfcal.io.bag import read_bag
from lrfcal.io.rig import ScanSource, ServoSource
from lrfcal.model.kinematics import DH, points_M
from lrfcal.stages.timing import scan_angles

REALBAGS = Path(__file__).resolve().parents[2] / "shared" / "realbags"
BANDS_M = (0.1, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 5.6)
#: the authors' model (nodes/point_cloud_from_slice_node.py: TILT_RADIUS = 0.08)
NOMINAL = DH(0.0, math.pi / 2, 0.08, 0.0)


def _read(name: str):  # type: ignore[no-untyped-def]
    return read_bag(REALBAGS / f"{name}.bag", ScanSource(topic="/slice", field="laserScan"),
                    ServoSource(topic=None, field="stepAngle", unit="deg", stamp="scan", motion="step"),
                    warn=lambda _: None)


def noise_by_range(name: str) -> list[str]:
    R = _read(name).scans.ranges_m
    d2, r = R[2:] - 2 * R[1:-1] + R[:-2], R[1:-1]
    ok = np.isfinite(d2)
    lines = []
    for lo, hi in zip(BANDS_M[:-1], BANDS_M[1:], strict=True):
        x = d2[ok & (r >= lo) & (r < hi)]
        if x.size < 1000:
            continue
        sigma = 1.4826 * np.median(np.abs(x - np.median(x))) / math.sqrt(6.0)
        lines.append(f"| {name} | {lo:g}-{hi:g} m | {x.size} | {sigma * 1000:.2f} mm |")
    return lines


def box_wiggle() -> list[str]:
    bd = _read("cardboard_box")
    scans = bd.scans
    lam = scan_angles(scans, bd.joints)
    S, N = scans.ranges_m.shape
    s, b = np.nonzero(np.isfinite(scans.ranges_m))
    p = points_M(scans.ranges_m[s, b], lam[s], scans.mu_rad[s, b], NOMINAL)
    fwd, up, left = p[:, 0], -p[:, 1], p[:, 2]  # x_M forward, y_M down, z_M left
    wall = (fwd > 0.27) & (up > -0.09) & (np.abs(left) < 0.12)  # the facing wall, away from its edges
    P, scan, beam = p[wall], s[wall], b[wall]
    c = P.mean(0)
    _, _, vt = np.linalg.svd(P - c, full_matrices=False)
    res, u, v = (P - c) @ vt[2], (P - c) @ vt[0], (P - c) @ vt[1]
    A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    res = res - A @ np.linalg.lstsq(A, res, rcond=None)[0]
    beams = np.unique(beam)
    quarters = np.quantile(scan, [0, 0.25, 0.5, 0.75, 1.0])
    pattern = np.full((4, beams.size), np.nan)
    for q in range(4):
        inq = (scan >= quarters[q]) & (scan < quarters[q + 1])
        for j, k in enumerate(beams):
            sel = inq & (beam == k)
            if sel.sum() > 50:
                pattern[q, j] = res[sel].mean()
    ok = np.all(np.isfinite(pattern), axis=0)
    corr = np.corrcoef(pattern[:, ok])
    mean = np.array([res[beam == k].mean() for k in beams])
    inner = (beams > beams.min() + 3) & (beams < beams.max() - 3)
    k, m = beams[inner].astype(float), mean[inner]
    m = m - np.polyval(np.polyfit(k, m, 2), k)
    F, f = np.abs(np.fft.rfft(m)), np.fft.rfftfreq(m.size)
    top = int(np.argmax(F[1:])) + 1
    return [f"box, facing wall: {wall.sum()} returns of {S} scans, beams {beams.min()}-{beams.max()}; residual "
            f"{res.std() * 1000:.2f} mm RMS; per-beam mean {m.std() * 1000:.2f} mm RMS",
            f"correlation of the per-beam pattern between quarters (1st and 4th, 2nd and 3rd at the same tilts): "
            f"{corr[0, 3]:.2f}, {corr[1, 2]:.2f}; at other tilts {corr[0, 1]:.2f}, {corr[0, 2]:.2f}, "
            f"{corr[1, 3]:.2f}, {corr[2, 3]:.2f}",
            f"strongest period {1 / f[top]:.1f} beams, amplitude {2 * F[top] / m.size * 1000:.2f} mm"]


def main() -> None:
    if not REALBAGS.is_dir():
        print(f"skipped: {REALBAGS} (the shared real recordings) is absent")
        return
    print("| recording | range | second differences | noise sigma |\n|---|---|---|---|")
    for name in ("cardboard_box", "room_240"):
        print("\n".join(noise_by_range(name)))
    print()
    print("\n".join(box_wiggle()))


if __name__ == "__main__":
    main()
