"""How much of a calibration's error is the model's own, not noise (issue 18, item 5: a sigma that includes model
error).

For each random truth of lrfsim.testing.random_scenarios.random_scenario_wide(seed, broad=True), the same recording is
simulated twice, once as shipped and once without range noise and with an exact tape (sigma 1 um). Both are
calibrated as shipped. An error that the noise-free, exact-map recording reproduces is the model's: noise
cannot make it, and the reported sigma, which is noise's, does not cover it. Prints per truth and recording
the DH errors in units of the reported sigma.

Seeds 28 and 67 (tilted spins) were the two largest alpha errors of
``bench_trust.py --broad --seeds 120`` (-3.3 sigma each); 6 and 12 are along the motor axis, for comparison.

With ``--per-marker``, per truth also the marker model's residuals AT THE TRUTH (the noise-free marker returns
and true marker positions of ``lrfsim plan``): per marker the mean whitened range, in-plane and across-plane
lateral residual, with the standard error of each mean over the marker's scan lines. The model takes every
return's residual as independent noise of mean 0; a mean many standard errors from 0 is a per-marker model error
(near perpendicular truth 5: the across-plane part, up to 12 standard errors on one marker; docs/study.md).

With ``--stated-sigma S`` the noise-free recording is calibrated again with the rig file's range noise replaced by S
(``--range-sigma``): the weight the range residuals get against the lateral ones, which do not scale with it. With
``--first-order``, the first-order shift from the truth that the noise-free residuals of the marker returns alone
make, -(J^T J)^-1 J^T r at the truth (marker-only, every lateral residual kept), in units of its sigma, and the part
of b's shift that each kind of residual and each marker makes (seed 1046, bench_promise's one confident wrong
before the marker surfaces' scan-line rule: docs/trust.md).

With ``--lateral-parts NAME ...`` (shipped scenarios) instead: is the marker model's lateral residual honest about
what it adds to the DH's error (issue 56, the stated sigma too wide on marker layouts)? Over ``--phases`` casts of each
scenario without noise (seeds 1..N: each a new laser phase on the markers, as a new recording is), the first-order DH
shift that each part of the residuals at the truth makes (marker returns alone, the lateral residual used where the
calibration uses it: markers crossed on both sides, lrfcal.model.marker.crossings, every crossing whole), in units of
the marker-only model sigma: its RMS over the phases ("actual") beside the part of the sigma the model gives it
("model", sqrt of that part's share of the variance). The range part's actual is the model's error alone (its noise
is drawn in a recording, not here); where the lateral parts' actual is below their model, the model counts a
marker's lateral offsets as independent draws where the beam grid makes them an even sample (docs/study.md).

    python benchmarks/bench_model_error.py [--seeds 28 67 6 12] [--per-marker] [--first-order] [--stated-sigma S]
    python benchmarks/bench_model_error.py --lateral-parts spinning_tilted plane_30deg tunnel_v [--phases 12]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path
from typing import Any

from lrfcal.model.kinematics import DH_NAMES
from lrfsim.scenario.file import Scenario
from lrfsim.simulation.recording import write_recording
from lrfsim.simulation.simulate import simulate
from lrfsim.testing.random_scenarios import alpha_kind_of, random_scenario_wide
from lrfsim.trials.trial import calibrate_recording

#: the tape's sigma of the "exact" map [m]
EXACT_TAPE_M = 1e-6


def _row(scenario: Scenario, noise: bool, folder: Path, stated_sigma_m: float | None = None) -> str:
    from lrfcal.config import CalibConfig

    if not folder.exists():
        write_recording(simulate(scenario, noise=noise), scenario, folder)
    config = None if stated_sigma_m is None else CalibConfig(baseline=False, geometry=False, clouds=False,
                                                              range_sigma_m=stated_sigma_m)
    trial = calibrate_recording(folder, config)
    if trial.status != "calibrated":
        return f"refused: {trial.reason[:100]}"
    parts = []
    for name, e, s, z in zip(DH_NAMES, trial.errors, trial.sigma, trial.z, strict=True):
        scale, unit = (math.degrees(1.0), "deg") if name in ("alpha", "beta") else (1000.0, "mm")
        parts.append(f"{name} {e * scale:+.3f} +- {s * scale:.3f} {unit} ({z:+.1f})")
    return ", ".join(parts)


def _at_truth(scenario: Scenario) -> tuple[Any, Any, Any, Any, Any]:
    """The noise-free marker returns of ``scenario`` at the truth (``lrfsim plan``'s): their observations, whitened
    residuals (K, 4: range, then the lateral residual in W), Jacobian (K, 4, 10), and per return the unit vectors in
    the scan plane across the beam and along the scan plane's normal (K, 3) each."""
    import numpy as np

    from lrfcal.estimate.information import model_residuals
    from lrfcal.model.kinematics import beam_rays_W
    from lrfcal.model.marker import MarkerSensor
    from lrfsim.plan.prediction import marker_observations

    obs, markers_W, params, _, _, _ = marker_observations(scenario)
    assert scenario.markers is not None
    sensor = MarkerSensor.of("sphere", float(scenario.markers.radius_m), float(scenario.sensor.divergence_rad))
    res, J = model_residuals(params, obs, markers_W, sensor=sensor)
    _, d = beam_rays_W(params, obs.lambda_rad, obs.mu_rad + 0.5 * math.pi)  # in the scan plane, across the beam
    _, d0 = beam_rays_W(params, obs.lambda_rad, obs.mu_rad)
    return obs, res.reshape(-1, 4), J.reshape(-1, 4, 10), d, np.cross(d0, d)


def first_order(scenario: Scenario) -> list[str]:
    """Lines of the first-order shift from the truth its noise-free marker residuals make (module docstring)."""
    import numpy as np

    obs, res, J, d, n = _at_truth(scenario)
    Jf = J.reshape(-1, 10)
    cov = np.linalg.pinv(Jf.T @ Jf)
    sigma = np.sqrt(np.diag(cov))[6:]

    def shift(r: Any) -> Any:
        return (-cov @ Jf.T @ r.ravel())[6:]

    lateral = res[:, 1:]
    parts = {"range": np.concatenate([res[:, :1], 0 * lateral], 1)}
    for name, u in (("in-plane lateral", d), ("across-plane lateral", n)):
        parts[name] = np.concatenate([0 * res[:, :1], (lateral * u).sum(1)[:, None] * u], 1)
    total = shift(res)
    out = ["    first-order shift / sigma: " + ", ".join(f"{k} {v:+.2f}" for k, v in zip(DH_NAMES, total / sigma,
                                                                                           strict=True))]
    out.append("    b's shift [mm] by part: " + ", ".join(f"{k} {shift(r)[2] * 1000:+.2f}" for k, r in parts.items()))
    per = []
    for m in np.unique(obs.marker):
        r = np.where((obs.marker == m)[:, None], res, 0.0)
        per.append((abs(shift(r)[2]), f"marker {m} {shift(r)[2] * 1000:+.2f}"))
    out.append("    b's shift [mm], largest markers: " + ", ".join(t for _, t in sorted(per, reverse=True)[:4]))
    return out


def per_marker(scenario: Scenario) -> list[str]:
    """Lines of the per-marker mean whitened residuals at the truth (module docstring)."""
    import numpy as np

    obs, res, _, d, n = _at_truth(scenario)
    parts = {"range": res[:, 0], "in-plane": (res[:, 1:] * d).sum(1), "across": (res[:, 1:] * n).sum(1)}
    out = []
    for m in np.unique(obs.marker):
        k = obs.marker == m
        lines = max(np.unique(obs.scan[k]).size, 1)
        se = {name: v[k].std() / math.sqrt(lines) for name, v in parts.items()}
        cells = [f"{name} {v[k].mean():+.2f}" + (f" ({v[k].mean() / se[name]:+.1f} se)" if lines > 1 and se[name] > 0
                                                 else "") for name, v in parts.items()]
        out.append(f"    marker {m:2d}: {int(k.sum()):4d} returns on {lines:3d} lines; " + ", ".join(cells))
    return out


def _lateral_parts(scenario: Scenario) -> dict[str, tuple[Any, Any]]:
    """Per part of the noise-free marker residuals at the truth of ``scenario`` (the lateral one where its marker is
    crossed on both sides): the first-order DH shift it makes and the model's sigma of that shift, both over the
    marker-only model sigma (4,) each (module docstring)."""
    import numpy as np

    obs, res, J, d, n = _at_truth(scenario)
    side = np.sign((res[:, 1:] * n).sum(1))  # the centre's side of the scan plane: the lateral residual's across part
    lo, hi = np.full(obs.marker.max() + 1, 2.0), np.full(obs.marker.max() + 1, -2.0)
    np.minimum.at(lo, obs.marker, side)
    np.maximum.at(hi, obs.marker, side)
    both = ((lo < 0) & (hi > 0))[obs.marker].astype(float)
    res, J = res.copy(), J.copy()
    res[:, 1:] *= both[:, None]
    J[:, 1:, :] *= both[:, None, None]
    Jf = J.reshape(-1, 10)
    cov = np.linalg.pinv(Jf.T @ Jf)
    sigma = np.sqrt(np.diag(cov))[6:]
    parts = {"range": (res[:, :1], J[:, :1, :])}
    for name, u in (("in-plane", d), ("across", n)):
        parts[name] = ((res[:, 1:] * u).sum(1)[:, None], np.einsum("ki,kij->kj", u, J[:, 1:, :])[:, None, :])
    out = {}
    for name, (r, Jp) in parts.items():
        Jp = Jp.reshape(-1, 10)
        shift = -(cov @ (Jp.T @ r.ravel()))[6:]
        model = np.sqrt(np.diag(cov @ Jp.T @ Jp @ cov)[6:])
        out[name] = (shift / sigma, model / sigma)
    return out


def lateral_parts(name: str, phases: int) -> list[str]:
    """Lines of the lateral parts' actual and model share for the shipped scenario ``name`` (module docstring)."""
    import numpy as np
    import yaml

    from lrfsim.scenario.file import parse_scenario

    data = yaml.safe_load((Path(__file__).resolve().parents[1] / "scenarios" / f"{name}.yaml").read_text())
    runs = []
    for seed in range(1, phases + 1):
        data["seed"] = seed
        runs.append(_lateral_parts(parse_scenario(data, name)))
    lines = [f"{name} ({phases} laser phases, marker returns alone, noise-free; a, alpha, b, beta):"]
    for part in runs[0]:
        actual = np.sqrt(np.mean([r[part][0] ** 2 for r in runs], axis=0))
        model = np.mean([r[part][1] for r in runs], axis=0)
        lines.append(f"  {part:9s} actual " + ", ".join(f"{v:.2f}" for v in actual)
                     + " | model " + ", ".join(f"{v:.2f}" for v in model))
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[28, 67, 6, 12])
    ap.add_argument("--per-marker", action="store_true", help="also the residuals at the truth, per marker")
    ap.add_argument("--first-order", action="store_true", help="also the first-order shift the truth's residuals make")
    ap.add_argument("--stated-sigma", type=float, default=None, metavar="S",
                    help="also the noise-free recording calibrated with a stated range noise of S [m]")
    ap.add_argument("--lateral-parts", nargs="+", default=None, metavar="NAME",
                    help="instead: the lateral residual's parts against the model on these shipped scenarios")
    ap.add_argument("--phases", type=int, default=12, help="laser phases (casts) per scenario for --lateral-parts")
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.lateral_parts:
        for name in args.lateral_parts:
            print("\n".join(lateral_parts(name, args.phases)), flush=True)
        print(f"benchmark wall time {time.perf_counter() - t0:.0f} s")
        return
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            sc = random_scenario_wide(seed, broad=True)
            exact = sc.model_copy(update={"tape": sc.tape.model_copy(update={"sigma_m": EXACT_TAPE_M})})
            print(f"seed {seed} ({alpha_kind_of(sc)}, alpha {math.degrees(sc.rig.dh.alpha):+.2f} deg):", flush=True)
            print(f"  as shipped:            {_row(sc, True, Path(tmp) / f'{seed}_noisy')}", flush=True)
            print(f"  no noise, exact tape:  {_row(exact, False, Path(tmp) / f'{seed}_exact')}", flush=True)
            if args.stated_sigma is not None:
                row = _row(exact, False, Path(tmp) / f"{seed}_exact", args.stated_sigma)
                print(f"  the same, {args.stated_sigma * 1000:g} mm stated: {row}", flush=True)
            if args.first_order:
                print("  at the truth, marker returns alone, noise-free:")
                print("\n".join(first_order(exact)), flush=True)
            if args.per_marker:
                print("  at the truth, mean whitened residual per marker (standard errors over its lines):")
                print("\n".join(per_marker(exact)), flush=True)
    print(f"benchmark wall time {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
