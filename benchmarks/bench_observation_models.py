"""The simulator's returns against the calibration's observation models, at the truth and without noise (issue 18,
item 5: where a bias that no noise makes can come from).

A scenario is simulated without range noise and range quantisation
(``lrfsim.simulation.simulate.simulate(noise=False)``; the beam's footprint, its 7 sub-rays and their power-weighted
range, stays) and every return is compared with what the calibration's models predict with the TRUE DH, mount, motor
angles and marker centres:

* surface returns (lrfcal.model.plane): the range against the ray's distance to the markers' plane moved back by
  the marker radius, for the rays that meet it inside the markers' extent (+5 cm) and 3 cm clear of every marker
  (the selection of lrfcal.stages.surfaces); mean per 10 deg of incidence;
* marker returns (lrfcal.model.marker, ``"sphere"`` with the footprint): the range against t - R S(u, k) for the
  rays whose measured point lies within 3 marker radii of a centre; mean per band of u, the ray's distance from the
  centre in marker radii (beyond u = 1 + k no part of the footprint meets the sphere: those are the surface behind).

A mean far from 0 (against the residuals' standard deviation) in a band the calibration uses is a model error of
that observation; means at the 0.01 mm level say the model is not where a bias of tenths of a millimetre comes from.

    python benchmarks/bench_observation_models.py [SCENARIO ...]   (default: plane_30deg, plane_0deg)

The markers must lie on one plane (the board scenarios; tunnel_v's V is two walls): others are skipped, named.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lrfcal.model.kinematics import Params, beam_rays_W
from lrfcal.model.marker import ray_to_centre
from lrfcal.model.sphere import footprint_depth
from lrfsim.scenario.file import load_scenario
from lrfsim.simulation.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
#: a surface return must lie this close to the model's range to be counted (the rest: other surfaces) [m]
SURFACE_GATE_M = 0.03
#: the bands of u (the ray's distance from a marker centre, in marker radii) of the marker table
U_BANDS = ((0.0, 0.3), (0.3, 0.6), (0.6, 0.8), (0.8, 0.95), (0.95, 1.05), (1.05, 1.2), (1.2, 1.5), (1.5, 3.0))


def _row(label: str, res_m: np.ndarray) -> str:
    return f"| {label} | {res_m.size} | {res_m.mean() * 1e3:+.3f} | {res_m.std() * 1e3:.3f} |"


def compare(scenario_path: Path) -> None:
    """Print the two tables of the module docstring for one scenario."""
    sc = load_scenario(scenario_path)
    sim = simulate(sc, noise=False)
    truth = sim.truth
    S, N = sim.ranges_m.shape
    o, d = beam_rays_W(Params(truth.mount, truth.dh), sim.beam_lambda_rad.ravel(),
                       np.broadcast_to(sim.mu_rad, (S, N)).ravel())
    r = sim.ranges_m.ravel()
    X, R = truth.markers_W, float(truth.marker_radius_m or 0.0)
    c = X.mean(0)
    _, spread, axes = np.linalg.svd(X - c)
    if spread[2] / np.sqrt(len(X)) > 0.001:
        print(f"\n{sc.name}: skipped, its markers are not on one plane (RMS {spread[2] / np.sqrt(len(X)) * 1e3:.0f} mm "
              "off the best one)")
        return
    n, off = axes[2], float(axes[2] @ c)
    if n @ truth.mount.matrix()[:3, 3] > off:  # the normal away from the sensor, the plane R behind the centres
        n, off = -n, -off
    off += R
    dn = d @ n
    t = (off - o @ n) / dn
    hit = o + t[:, None] * d
    q, qm = (hit - c) @ axes[:2].T, (X - c) @ axes[:2].T
    inside = np.all((q >= qm.min(0) - 0.05) & (q <= qm.max(0) + 0.05), axis=1)
    res = r - t
    surface = np.isfinite(r) & (t > 0) & inside & (cKDTree(X).query(hit)[0] >= 0.03) & (np.abs(res) < SURFACE_GATE_M)
    incidence = np.degrees(np.arccos(np.minimum(np.abs(dn), 1.0)))
    print(f"\n{sc.name}: surface returns, simulated range - ray-plane distance [mm]\n")
    print("| incidence [deg] | returns | mean | sd |\n|---|---|---|---|")
    print(_row("all", res[surface]))
    for lo in range(0, 90, 10):
        band = surface & (incidence >= lo) & (incidence < lo + 10)
        if band.any():
            print(_row(f"{lo}-{lo + 10}", res[band]))

    finite = np.isfinite(r)
    near, j = cKDTree(X).query(o + np.where(finite, r, 0.0)[:, None] * d)
    mk = finite & (near < 3.0 * R)
    _, tt, e = ray_to_centre(o[mk], d[mk], X[j[mk]])
    u = np.linalg.norm(e, axis=1) / R
    k = r[mk] * sc.sensor.divergence_rad / (2.0 * R)
    depth, _ = footprint_depth(u, k)
    res_mk = r[mk] - (tt - R * depth)
    print(f"\n{sc.name}: returns near markers, simulated range - t + R S(u, k) [mm] (footprint k: median "
          f"{np.median(k):.2f} marker radii)\n")
    print("| u (ray to centre / R) | returns | mean | sd |\n|---|---|---|---|")
    for lo, hi in U_BANDS:
        band = (u >= lo) & (u < hi)
        if band.any():
            print(_row(f"{lo:.2f}-{hi:.2f}", res_mk[band]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="*", type=Path,
                    default=[ROOT / "scenarios" / "plane_30deg.yaml", ROOT / "scenarios" / "plane_0deg.yaml"])
    for path in ap.parse_args().scenarios:
        compare(path)


if __name__ == "__main__":
    main()
