"""`lrfcal reproject` speed on a simulated tunnel_v recording, against a plain numpy per-scan loop.

    python benchmarks/bench_reproject.py [--scenario scenarios/tunnel_v.yaml] [--repeat 3]

Measured in the same run, on the same beams:

1. ``lrfcal reproject`` end to end in-process (lrfcal.commands.reproject.reproject_bag: read the bag, reproject every
beam
   at its own time and motor angle, write the PLY), beams per second;
2. the reprojection alone (lrfcal.commands.reproject.reproject_beams) against a plain numpy loop over the scans (per
scan:
   beam times, np.interp of the motor angle, the eq. (3) chain as 4x4 matrices per beam), beams per second and
   the ratio; the two clouds are checked to agree to 1e-9 m;
3. the time to write the PLY of ~1.6 M points (write_cloud_ply, atomic).

Prints the numbers; exits 0 (it reports, the tests assert).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from lrfcal.commands.reproject import BeamCloud, CloudOutputs, reproject_bag, reproject_beams, write_cloud_ply
from lrfcal.io.recording import read_recording
from lrfcal.model.kinematics import DH
from lrfsim.scenario.file import load_scenario
from lrfsim.simulation.to_folder import simulate_to_folder

ROOT = Path(__file__).resolve().parents[1]


def numpy_loop(scans, joints, dh: DH) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The straightforward way: per scan, per-beam times and motor angles, then T_M_L per beam as the product of
    the eq. (3) elementary 4x4 matrices, applied to [r, 0, 0, 1]."""
    def rz(t: np.ndarray) -> np.ndarray:
        c, s = np.cos(t), np.sin(t)
        m = np.zeros(t.shape + (4, 4))
        m[..., 0, 0], m[..., 0, 1], m[..., 1, 0], m[..., 1, 1] = c, -s, s, c
        m[..., 2, 2] = m[..., 3, 3] = 1.0
        return m

    ca, sa = np.cos(dh.alpha), np.sin(dh.alpha)
    fixed = np.array([[1, 0, 0, dh.a], [0, ca, -sa, -sa * dh.b], [0, sa, ca, ca * dh.b], [0, 0, 0, 1.0]])
    out = []
    for k in range(scans.stamps_s.size):
        r = scans.ranges_m[k]
        ok = np.flatnonzero(np.isfinite(r))
        t = scans.stamps_s[k] + ok * scans.time_increment_s[k]
        lam = np.interp(t, joints.stamps_s, joints.positions_rad)
        T = rz(lam) @ fixed @ rz(dh.beta + scans.mu_rad[k, ok])
        p = np.stack([r[ok], np.zeros(ok.size), np.zeros(ok.size), np.ones(ok.size)], -1)
        out.append(np.einsum("kij,kj->ki", T, p)[:, :3])
    return np.concatenate(out)


def best_of(n: int, fn):  # type: ignore[no-untyped-def]
    best, value = float("inf"), None
    for _ in range(n):
        t0 = time.perf_counter()
        value = fn()
        best = min(best, time.perf_counter() - t0)
    return best, value


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", type=Path, default=ROOT / "scenarios" / "tunnel_v.yaml")
    ap.add_argument("--repeat", type=int, default=3, help="timings are the best of this many runs (default 3)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        t0 = time.perf_counter()
        simulate_to_folder(load_scenario(args.scenario), tmp_path / "rec")
        print(f"simulated {args.scenario.name} in {time.perf_counter() - t0:.1f} s")
        rec_dir = tmp_path / "rec"
        nominal = rec_dir / "nominal.yaml"
        dh = DH(**yaml.safe_load(nominal.read_text())["dh"])
        rec = read_recording(rec_dir, require_distances=False)
        covered_all = True
        t_api, cloud = best_of(args.repeat, lambda: reproject_beams(rec.scans, rec.joints, dh))
        assert isinstance(cloud, BeamCloud)
        covered_all = cloud.n_scans_uncovered == 0
        n = len(cloud)
        # the loop over the same beams: the covered scans only
        t_loop, pts = best_of(args.repeat, lambda: numpy_loop(rec.scans, rec.joints, dh))
        if covered_all:
            err = float(np.max(np.abs(pts - cloud.points_M)))
            print(f"clouds agree: max |difference| {err:.2e} m")
            assert err < 1e-9
        t_cli, _ = best_of(args.repeat,
                           lambda: reproject_bag(rec_dir / "bag", nominal, CloudOutputs(tmp_path / "cli.ply")))
        t_ply, _ = best_of(args.repeat, lambda: write_cloud_ply(tmp_path / "w.ply", cloud))
        size_mb = (tmp_path / "w.ply").stat().st_size / 1e6
    print(f"beams (valid returns): {n} of {rec.scans.stamps_s.size} scans")
    print(f"lrfcal reproject end to end (read bag + reproject + write PLY): {t_cli:.2f} s = {n / t_cli / 1e6:.2f} M "
          f"beams/s")
    print(f"reprojection alone: {t_api:.3f} s = {n / t_api / 1e6:.2f} M beams/s; plain numpy per-scan loop: "
          f"{t_loop:.3f} s = {n / t_loop / 1e6:.2f} M beams/s; ratio {t_loop / t_api:.1f}x")
    print(f"PLY of {n / 1e6:.2f} M points ({size_mb:.0f} MB): {t_ply:.2f} s")


if __name__ == "__main__":
    main()
