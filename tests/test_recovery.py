"""Parameter recovery, system-identification style: simulate with a known truth, write the recording, read it back
from disk as a real one, calibrate from the perturbed nominal start, and assert that the truth comes back within
stated absolute bounds and within 4 sigma of the covariance the calibration reports.

1. 20 seeded random ground truths (lrfsim.testing.random_scenarios.random_scenario: random DH, mount pose, marker
   layout and noise level), one quick sweep each;
2. the shipped scenarios (scenarios/*.yaml), each against its own tolerances and the issue's tunnel target;
3. the covariance itself: pooled over the random cases, error / sigma has an RMS near 1.

Every case is computed once per session (lazily, so `-k` selections compute only what they need).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import tiered

from lrfcal.io.recording import read_recording
from lrfcal.model.kinematics import DH_NAMES, PARAM_NAMES
from lrfcal.pipeline import CalibConfig, calibrate
from lrfcal.result import CalibrationResult, MarkerEvidence, Matched, Observer
from lrfsim.scenario.file import Scenario, load_scenario
from lrfsim.scenario.sections import Tolerances
from lrfsim.simulation.simulate import systematic_truth
from lrfsim.testing.random_scenarios import random_scenario
from lrfsim.trials.compare import Comparison, compare, load_truth

SCENARIOS = {p.stem: p for p in sorted((Path(__file__).resolve().parents[1] / "scenarios").glob("*.yaml"))}
MARKERLESS = {name for name, path in SCENARIOS.items() if load_scenario(path).markers is None}
#: the shipped scenarios with markers; the marker-less ones (room_box, cardboard_box) are calibrated targetless once
#: in tests/test_targetless.py, which checks their 4 sigma and their scenario's tolerances (cardboard_box with -m slow)
SHIPPED = [name for name in SCENARIOS if name not in MARKERLESS]
SEEDS = tuple(range(20))
IN_SUITE = 8  # the random truths the suite runs (the rest with -m slow: tests/conftest.py, tiered)
N_SIGMA = 4.0
DH_INDEX = tuple(PARAM_NAMES.index(n) for n in DH_NAMES)  # a, alpha, b, beta in the (10,) sigma

#: Absolute bounds for the random cases, from what they measure (seeds 0-19, commit 243828e) with margin. One pass
#: at 20 deg/s sees each 5 mm marker with only 1-4 beams (16-43 returns in all on 10-20 markers), so some layouts
#: leave a and b weakly determined: reported sigma(a), sigma(b) reach 9 and 15 mm. Worst measured errors:
#: a 12.3 mm, b 12.1 mm, alpha 0.31 deg, beta 0.49 deg, mount 16.3 mm / 0.47 deg; tunnel dimensions 0.8 mm.
#: The sharp per-case check is the 4-sigma one; these catch a calibration that goes astray (a flipped alpha,
#: a diverged b, a wrong association), which they would by orders of magnitude.
RANDOM_BOUNDS = Tolerances(
    a_m=0.020,
    b_m=0.020,
    alpha_rad=math.radians(0.75),
    beta_rad=math.radians(0.75),
    position_m=0.025,
    rotation_rad=math.radians(0.75),
    tunnel_m=0.005,
)
#: The issue's target for the tunnel dimensions from the calibrated cloud (paper Table III: 8 / 20 / 20 mm).
TUNNEL_TARGET_M = 0.003
#: Accepted RMS of the pooled normalised errors err / sigma (1 if the covariance is right).
Z_RMS_RANGE = (0.5, 2.0)


@dataclass(frozen=True)
class Case:
    """One simulate + calibrate run: the comparison with the truth, DH errors, reported sigma and err / sigma,
    each (4,) in DH_NAMES order (a, alpha, b, beta)."""

    name: str
    result: CalibrationResult
    comparison: Comparison
    errors: np.ndarray
    sigma: np.ndarray
    seconds: float
    fitted: tuple[CalibrationResult, ...] = ()  # what the observer's fitted was told, before the clouds
    matched: tuple[Matched, ...] = ()  # what the observer's matched was told (the marker way's association)

    @property
    def z(self) -> np.ndarray:
        return self.errors / self.sigma

    def describe(self) -> str:
        """Table I in one line, for failure messages."""
        parts = []
        for name, e, s in zip(DH_NAMES, self.errors, self.sigma, strict=True):
            scale, unit = (1000.0, "mm") if name in ("a", "b") else (math.degrees(1.0), "deg")
            parts.append(f"{name} {e * scale:+.3f} +- {s * scale:.3f} {unit} ({e / s:+.1f} sigma)")
        c = self.comparison
        parts.append(
            f"mount {c.mount_position_error_m * 1000:.2f} mm / {math.degrees(c.mount_rotation_error_rad):.3f} deg"
        )
        parts += [
            f"{r.name} {'-' if r.calibrated is None else f'{(r.calibrated - r.truth) * 1000:+.1f}'} mm"
            for r in c.tunnel_rows
        ]
        return f"{self.name}: " + "; ".join(parts) + f"; {self.result.solution.status}"


def run_case(scenario: Scenario, folder: Path, tolerances: Tolerances | None = None, baseline: bool = True) -> Case:
    """Read the recording of ``scenario`` back from ``folder`` (simulated and written there by the session's
    ``recording_of``, tests/conftest.py), calibrate (with the paper's method beside it when ``baseline``), compare
    (against ``tolerances``, default the scenario's own)."""
    recording = read_recording(folder, require_distances=(folder / "distances.csv").exists())
    t0 = time.perf_counter()
    told = _Told()
    result = calibrate(recording, CalibConfig(range_sigma_m=0.010, baseline=baseline), told)
    seconds = time.perf_counter() - t0
    comparison = compare(result, load_truth(folder / "ground_truth.yaml"), tolerances or scenario.tolerances)
    errors = np.array([row.error for row in comparison.dh_rows])
    assert [row.name for row in comparison.dh_rows] == list(DH_NAMES)
    return Case(scenario.name, result, comparison, errors, result.solution.sigma[list(DH_INDEX)], seconds,
                tuple(told.results), tuple(told.associations))


class _Told(Observer):
    """What a calibration told its observer (lrfcal.result.Observer)."""

    def __init__(self) -> None:
        super().__init__()
        self.results: list[CalibrationResult] = []
        self.associations: list[Matched] = []

    def matched(self, matched: Matched) -> None:
        self.associations.append(matched)

    def fitted(self, result: CalibrationResult) -> None:
        self.results.append(result)


class _Cases:
    """Lazily computed, session-wide cache of cases by key."""

    def __init__(self, make: Callable[[object], Case]) -> None:
        self._make = make
        self._done: dict[object, Case] = {}

    def __getitem__(self, key: object) -> Case:
        if key not in self._done:
            self._done[key] = self._make(key)
        return self._done[key]


@pytest.fixture(scope="session")
def random_cases(recording_of: Callable[[Scenario], Path]) -> _Cases:
    def make(seed: object) -> Case:
        assert isinstance(seed, int)
        scenario = random_scenario(seed)
        return run_case(scenario, recording_of(scenario), RANDOM_BOUNDS, baseline=False)  # checked on the shipped

    return _Cases(make)


@pytest.fixture(scope="session")
def shipped_cases(recording_of: Callable[[Scenario], Path]) -> _Cases:
    def make(name: object) -> Case:
        assert isinstance(name, str)
        scenario = load_scenario(SCENARIOS[name])
        return run_case(scenario, recording_of(scenario))

    return _Cases(make)


def within_sigma(case: Case) -> list[str]:
    """The DH parameters whose error exceeds N_SIGMA reported sigma."""
    return [
        f"{n} {z:+.2f} sigma" for n, z in zip(DH_NAMES, case.z, strict=True) if not abs(z) <= N_SIGMA
    ]


# --- 1. random ground truths ------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", tiered(SEEDS, keep=IN_SUITE))
def test_random_truth_is_recovered(seed: int, random_cases: _Cases) -> None:
    case = random_cases[seed]
    truth, start = case.comparison, case.result.start
    # the calibration really started away from the truth (nominal alpha, beta are exactly +-90 deg)
    assert any(
        abs(getattr(start.dh, r.name) - r.truth) > 1e-4 for r in truth.dh_rows if r.name in ("alpha", "beta")
    ), case.describe()
    failures = [f for f in case.comparison.failures if not f.startswith("tunnel ")]
    assert not failures, f"outside the absolute bounds: {failures}\n{case.describe()}"
    assert not within_sigma(case), f"error beyond {N_SIGMA} sigma: {within_sigma(case)}\n{case.describe()}"
    # the calibrated cloud subtracts the estimated range offset: each dimension (two walls apart) carries twice its
    # uncertainty, which a few surface returns leave at a few mm (4 sigma of it on top of the absolute bound)
    s_off = case.result.solution.range_offset_sigma_m
    bound = RANDOM_BOUNDS.tunnel_m + (8.0 * s_off if math.isfinite(s_off) else 0.0)
    for r in case.comparison.tunnel_rows:
        assert r.calibrated is not None and abs(r.calibrated - r.truth) <= bound, (r, bound, case.describe())


@pytest.mark.parametrize("n_seeds", tiered([IN_SUITE, len(SEEDS)]))
def test_reported_sigma_is_honest(random_cases: _Cases, n_seeds: int) -> None:
    """Pooled over the random cases (the suite's, or all with -m slow), err / sigma of a, b, alpha, beta has an RMS
    near 1: the reported covariance is neither wildly optimistic (RMS >> 1) nor pessimistic (RMS << 1)."""
    z = np.array([random_cases[seed].z for seed in SEEDS[:n_seeds]])  # (seeds, 4)
    rms = float(np.sqrt(np.mean(z**2)))
    per_param = ", ".join(f"{n} {np.sqrt(np.mean(z[:, i] ** 2)):.2f}" for i, n in enumerate(DH_NAMES))
    lo, hi = Z_RMS_RANGE
    assert lo <= rms <= hi, f"RMS of err/sigma over {z.size} values: {rms:.2f} (per parameter: {per_param})"


# --- 2. the shipped scenarios -----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_dh_within_4_sigma(name: str, shipped_cases: _Cases) -> None:
    case = shipped_cases[name]
    assert not within_sigma(case), f"error beyond {N_SIGMA} sigma: {within_sigma(case)}\n{case.describe()}"


def test_shipped_fitted_result_comes_before_the_clouds_and_is_the_results(shipped_cases: _Cases) -> None:
    """What the figures are drawn from during the reprojection (lrfcal.commands.calibrate): the result without its
    clouds."""
    case = shipped_cases[SHIPPED[0]]
    assert len(case.fitted) == 1
    early = case.fitted[0]
    assert early.cloud_after_M.size == 0 and case.result.cloud_after_M.size > 0
    assert early.solution is case.result.solution and early.evidence is case.result.evidence
    # the intensity figure's inputs, told once the alternative is chosen (drawn while the surfaces are fitted)
    assert len(case.matched) == 1
    out, ev = case.matched[0], case.result.evidence
    assert isinstance(ev, MarkerEvidence)
    assert out.detections is ev.detections and out.association is ev.association
    assert out.markers is ev.markers and out.scans is case.result.recording.scans


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_paper_baseline_present(name: str, shipped_cases: _Cases) -> None:
    case = shipped_cases[name]
    assert isinstance(case.result.evidence, MarkerEvidence)
    baseline = case.result.evidence.baseline
    assert baseline is not None, "the paper's baseline did not run"
    assert np.all(np.isfinite(baseline.params.vector())), baseline.status
    assert all(row.paper is not None for row in case.comparison.dh_rows)


def _idealised(name: str) -> bool:
    """The scenario's scanner has no systematic range errors (lrfsim.simulation.simulate.systematic_truth)."""
    return systematic_truth(load_scenario(SCENARIOS[name]).sensor) is None


@pytest.mark.parametrize("name", [n for n in SCENARIOS if n.startswith("tunnel") and _idealised(n)])
def test_shipped_tunnel_dimensions(name: str, shipped_cases: _Cases) -> None:
    """The issue's target: width, height and plate distance from the calibrated cloud within 3 mm (with the idealised
    scanner; a scenario with systematic range errors is held to its own tunnel_m, docs/sensor_errors.md)."""
    rows = shipped_cases[name].comparison.tunnel_rows
    assert {r.name for r in rows} == {"width", "height", "plate_distance"}
    for r in rows:
        assert r.calibrated is not None, f"{r.name}: no plane found in the calibrated cloud"
        assert abs(r.calibrated - r.truth) <= TUNNEL_TARGET_M, (
            f"{r.name}: calibrated {r.calibrated * 1000:.1f} mm vs truth {r.truth * 1000:.1f} mm "
            f"(nominal cloud {'-' if r.nominal is None else f'{r.nominal * 1000:.1f}'} mm)"
        )


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_scenario_tolerances(name: str, shipped_cases: _Cases) -> None:
    """The scenario's own tolerances (what `lrfsim run` reports as MISSED)."""
    case = shipped_cases[name]
    hint = (
        " [plane_*: the coplanar board is the hard case (board MDS, a/b coupling along the motor axis); "
        "report these numbers to the estimator's owner rather than widening the scenario's tolerances]"
        if name.startswith("plane")
        else ""
    )
    assert case.comparison.ok, f"MISSED {case.comparison.failures}{hint}\n{case.describe()}"
