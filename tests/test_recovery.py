"""Parameter recovery, system-identification style: simulate with a known truth, calibrate from the recording on
disk (perturbed nominal start), and assert that the truth comes back within stated bounds and within 4 sigma of
the covariance the calibration reports."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lrfcal.pipeline import calibrate
from lrfcal.recording import read_recording
from lrfsim.compare import Comparison, compare, load_truth
from lrfsim.randomize import random_scenario
from lrfsim.scenario import Scenario, Tolerances, load_scenario
from lrfsim.simulate import simulate, write_recording

SCENARIOS = sorted((Path(__file__).resolve().parents[1] / "scenarios").glob("*.yaml"))
SEEDS = range(20)
DH_INDEX = {"a": 6, "alpha": 7, "b": 8, "beta": 9}  # in PARAM_NAMES order
#: Bounds for the random cases: one quick pass at 20 deg/s over 10-20 scattered markers with 5-15 mm range noise
#: is little data, and some random layouts leave a - b poorly determined (reported sigma up to ~9 mm): measured
#: worst cases over seeds 0-19 were 12.3 mm (a, b), 0.49 deg (beta), 16 mm / 0.47 deg (mount). The sharp check
#: is the 4-sigma one; these bounds catch a calibration that goes astray.
RANDOM_BOUNDS = Tolerances(a_m=0.020, b_m=0.020, alpha_rad=math.radians(0.75), beta_rad=math.radians(0.75),
                           position_m=0.025, rotation_rad=math.radians(0.75), tunnel_m=0.005)


def _simulate_and_calibrate(scenario: Scenario, folder: Path) -> tuple[Comparison, np.ndarray]:
    """Returns the comparison with the truth and the DH errors / reported sigma (4,)."""
    write_recording(simulate(scenario), scenario, folder)
    result = calibrate(read_recording(folder))
    comparison = compare(result, load_truth(folder / "ground_truth.yaml"), scenario.tolerances)
    sigma = result.solution.sigma
    z = np.array([row.error / sigma[DH_INDEX[row.name]] for row in comparison.dh_rows])
    return comparison, z


@pytest.fixture(scope="session")
def random_cases(tmp_path_factory: pytest.TempPathFactory) -> dict[int, tuple[Comparison, np.ndarray]]:
    root = tmp_path_factory.mktemp("random")
    return {seed: _simulate_and_calibrate(random_scenario(seed), root / f"seed{seed}") for seed in SEEDS}


@pytest.mark.parametrize("seed", SEEDS)
def test_random_truth_is_recovered(seed: int, random_cases: dict[int, tuple[Comparison, np.ndarray]]) -> None:
    comparison, z = random_cases[seed]
    bounded = compare_bounds(comparison, RANDOM_BOUNDS)
    assert not bounded, f"seed {seed}: " + "; ".join(bounded)
    assert np.all(np.abs(z) <= 4.0), f"seed {seed}: DH errors / sigma = {np.round(z, 2)} (a, alpha, b, beta)"


def test_reported_sigma_is_honest(random_cases: dict[int, tuple[Comparison, np.ndarray]]) -> None:
    """Pooled over the random cases, error / sigma has an RMS near 1: the covariance is neither wildly
    optimistic (RMS >> 1) nor pessimistic (RMS << 1)."""
    z = np.concatenate([zs for _, zs in random_cases.values()])
    rms = float(np.sqrt(np.mean(z**2)))
    assert 0.5 <= rms <= 2.0, f"RMS of error/sigma over {z.size} values: {rms:.2f}"


def compare_bounds(c: Comparison, bounds: Tolerances) -> list[str]:
    """The comparison's failures against other bounds than the scenario's own."""
    out = []
    limits = {"a": bounds.a_m, "b": bounds.b_m, "alpha": bounds.alpha_rad, "beta": bounds.beta_rad}
    out += [f"{r.name}: |error| {abs(r.error):.3g} > {limits[r.name]:.3g}" for r in c.dh_rows
            if abs(r.error) > limits[r.name]]
    if c.mount_position_error_m > bounds.position_m:
        out.append(f"mount position error {c.mount_position_error_m:.4f} m")
    if c.mount_rotation_error_rad > bounds.rotation_rad:
        out.append(f"mount rotation error {math.degrees(c.mount_rotation_error_rad):.3f} deg")
    return out


@pytest.mark.parametrize("path", SCENARIOS, ids=[p.stem for p in SCENARIOS])
def test_shipped_scenario(path: Path, tmp_path: Path) -> None:
    scenario = load_scenario(path)
    comparison, z = _simulate_and_calibrate(scenario, tmp_path / "recording")
    assert np.all(np.abs(z) <= 4.0), f"DH errors / sigma = {np.round(z, 2)} (a, alpha, b, beta)"
    assert comparison.paper_mount_position_error_m is not None, "the paper's baseline did not run"
    assert comparison.ok, "; ".join(comparison.failures)
    for row in comparison.tunnel_rows:  # tunnel_v: the 3 mm on width, height and plate distance
        assert row.calibrated is not None and abs(row.calibrated - row.truth) <= 0.003, row
