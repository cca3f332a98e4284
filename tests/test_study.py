"""lrfsim study (issue 10): Monte-Carlo trials, the same table from one process, a process pool and dask."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrfcal.errors import InputError
from lrfcal.estimate.observability import LIMITS
from lrfcal.model.kinematics import DH_NAMES
from lrfsim.plan.prediction import plan
from lrfsim.scenario.file import parse_scenario
from lrfsim.testing.random_scenarios import random_scenario_wide
from lrfsim.trials.study import run_trials, study
from lrfsim.trials.study_result import (
    CSV_COLUMNS,
    DRAWS,
    FORCED,
    SELECTED,
    Study,
    StudyPart,
    exact_interval,
    p_exact,
    summary_markdown,
    trials_csv,
    write_study,
)
from lrfsim.trials.variants import PERTURB_HALF_WIDTH, parse_vary, perturbed_start, with_field

ROOT = Path(__file__).resolve().parents[1]
LRFSIM = [sys.executable, "-m", "lrfsim.cli"]


def _tiny_data() -> dict:
    """tunnel_v, one pass over +-69 deg at 45 deg/s: a trial in about a second, and it calibrates. (At 90 deg/s each
    marker is crossed by one scan line, which the marker-only fit cannot always tell from a moved marker: the
    calibration then judges it at the joint solution, 2-4 s a trial; that regime is tests/test_trust.py's
    fast single sweep, not this module's subject.)"""
    data = yaml.safe_load((ROOT / "scenarios" / "tunnel_v.yaml").read_text())
    data["servo"].update({"speed_rad_s": math.radians(45.0), "passes": 1, "start_rad": 1.2, "end_rad": -1.2})
    data["name"] = "tiny"
    return data


@pytest.fixture(scope="module")
def tiny():
    return parse_scenario(_tiny_data(), "tiny")


@pytest.fixture(scope="module")
def serial(tiny):
    return study(tiny, 3, seed0=10, workers=1)


def test_study_table(serial, tmp_path: Path) -> None:
    out = write_study(serial, tmp_path / "study")
    with (out / "trials.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert tuple(rows[0]) == CSV_COLUMNS
    for col in ("trial", "seed", "status", "reason", *(f"{p}_{k}" for p in DH_NAMES for k in ("error", "sigma"))):
        assert col in rows[0]
    assert [int(r["trial"]) for r in rows] == [0, 1, 2] and [int(r["seed"]) for r in rows] == [10, 11, 12]
    # tiny's one quick pass is at the edge of what determines the DH: a trial is right within its sigma or refused
    # with the reason (seed 12: its marker-only fit disagrees with the marker map but does not determine the DH,
    # lrfcal.stages.markers), and the table and summary say which
    calibrated = [r for r in rows if r["status"] == "calibrated"]
    refused = [r for r in rows if r["status"] != "calibrated"]
    assert len(calibrated) >= 2, [r["reason"] for r in rows]
    assert all(r["status"] == "refused" and r["exit_code"] == "3" and ":" in r["reason"] for r in refused), refused
    for r in calibrated:
        for p in DH_NAMES:
            sigma = float(r[f"{p}_sigma"])
            assert 0 < sigma < (1e-3 if p in ("a", "b") else math.radians(0.1))
            assert abs(float(r[f"{p}_error"])) < 5 * sigma
    # different seeds, different noise
    assert len({r["a_error"] for r in calibrated}) == len(calibrated)
    summary = (out / "summary.md").read_text()
    assert "RMSE / predicted" in summary and f"refusal rate {100 * len(refused) / 3:.0f} %" in summary
    assert DRAWS["noise"] in summary  # one cast for every trial: says what that hides and how to measure it
    # what the calibrated trials can tell: an exact sigma's RMS spread over as many trials
    lo, hi = exact_interval(len(calibrated))
    assert f"over {len(calibrated)} trials lies in {lo:.2f}-{hi:.2f}" in summary
    recast = summary_markdown(replace(serial, draws="cast"))
    assert DRAWS["cast"] in recast and DRAWS["noise"] not in recast
    # with some trials refused, the summary says the RMS is over the calibrated ones, which a refusal can select
    assert (SELECTED.format(n=len(calibrated)) in summary) == bool(refused)
    part = serial.parts[0]
    one_refused = (replace(part.rows[0], status="refused", reason="observability: b"), *part.rows[1:])
    mixed = summary_markdown(replace(serial, parts=(replace(part, rows=one_refused),)))
    n_mixed = sum(r.status == "calibrated" for r in one_refused)
    assert n_mixed > 0 and SELECTED.format(n=n_mixed) in mixed
    for p in DH_NAMES:
        assert (out / f"hist_{p}.png").read_bytes()[:4] == b"\x89PNG"
    assert serial.parts[0].plan is not None and serial.parts[0].plan.sigma["a"] > 0


def test_exact_sigma_interval_and_p_value() -> None:
    """An exact sigma's RMS of error / sigma over n trials is sqrt(chi2_n / n): 0.72-1.28 over 24 (95 %), 0.90-1.10
    over 200; the two-sided p-value of an RMS at the interval's ends is 0.05, of 1 about 0.9, of 0.54 over 24
    (V 2003's beta at the bound) 0.0006; over 24 normal draws it falls below 0.05 in about 5 % of the draws."""
    assert exact_interval(24) == pytest.approx((0.7188, 1.2807), abs=1e-4)
    assert exact_interval(200) == pytest.approx((0.902, 1.098), abs=1e-3)
    lo, hi = exact_interval(24)
    assert p_exact(lo, 24) == pytest.approx(0.05) and p_exact(hi, 24) == pytest.approx(0.05)
    assert p_exact(1.0, 24) > 0.9 and p_exact(0.54, 24) == pytest.approx(0.00058, abs=2e-5)
    assert math.isnan(p_exact(1.0, 0))
    rng = np.random.default_rng(3)
    rms = np.sqrt((rng.standard_normal((4000, 24)) ** 2).mean(1))
    assert 0.04 <= np.mean([p_exact(float(v), 24) < 0.05 for v in rms]) <= 0.06


def test_a_forced_study_calibrates_the_trials_the_checks_refuse() -> None:
    """Near a limit the checks' refusals can select the calibrated trials (those refused had the larger errors on
    points 2014: docs/study.md); ``force`` calibrates them as `lrfcal calibrate --force` does, and the summary says
    so. On points 2014's shared cast, seed 2015's b is over its 5 mm limit (without force: refused for
    observability, "weakest direction b against a at 1.1 of the limit"): calibrated with that sigma."""
    sc = random_scenario_wide(2014, layout="scattered")
    (forced,) = run_trials(sc, 1, seed0=2015, force=True)
    b = DH_NAMES.index("b")
    assert forced.status == "calibrated" and forced.sigma[b] > LIMITS["b"], forced
    assert all(math.isfinite(v) for v in forced.errors)
    part = StudyPart(value="", scenario=sc, plan=None, rows=(forced,))
    summary = summary_markdown(Study(name=sc.name, key=None, parts=(part,), seconds=0.0, forced=True))
    assert FORCED in summary and "calibrated 1 of 1" in summary


def test_process_pool_gives_the_same_table(tiny, serial, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two workers share one cast, which plan reads too (no cast of its own): the same table and prediction."""
    import lrfsim.trials.study as study_module

    given = []

    def spy(sc, **kw):
        given.append(kw.get("geometry"))
        return plan(sc, **kw)

    monkeypatch.setattr(study_module, "plan", spy)
    pooled = study(tiny, 3, seed0=10, workers=2)
    assert len(given) == 1 and given[0] is not None
    assert trials_csv(pooled) == trials_csv(serial)
    mine, theirs = pooled.parts[0].plan, serial.parts[0].plan
    assert mine is not None and theirs is not None
    for n in theirs.names:
        assert mine.sigma[n] == pytest.approx(theirs.sigma[n], rel=1e-9), n


def test_dask_local_cluster_gives_the_same_table(tiny, serial) -> None:
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as lc, \
            distributed.Client(lc) as client:
        rows = run_trials(tiny, 3, seed0=10, dask=client, batch_size=2)  # 2 tasks: batches of 2 and 1 trials
    pooled = type(serial)(name=serial.name, key=None, parts=(type(serial.parts[0])(
        value="", scenario=tiny, plan=None, rows=tuple(rows)),), seconds=0.0)
    assert trials_csv(pooled) == trials_csv(serial)


def test_vary_parsing_and_fields(tiny) -> None:
    assert parse_vary("servo.passes=1,2,4") == ("servo.passes", [1, 2, 4])
    assert parse_vary("faults.range_noise_scale=1, 2.5") == ("faults.range_noise_scale", [1, 2.5])
    assert with_field(tiny, "servo.passes", 2).servo.passes == 2
    with pytest.raises(InputError, match="no field"):
        with_field(tiny, "servo.pases", 2)
    with pytest.raises(InputError):
        with_field(tiny, "servo.passes", -1)
    with pytest.raises(InputError, match="KEY=V1"):
        parse_vary("servo.passes")


def test_study_cli_vary(tmp_path: Path) -> None:
    scen = tmp_path / "tiny.yaml"
    scen.write_text(yaml.safe_dump(_tiny_data()))
    out = tmp_path / "out"
    proc = subprocess.run([*LRFSIM, "study", scen, "--trials", "1", "-o", out, "--vary",
                           "faults.range_noise_scale=1,2"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    with (out / "trials.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["value"] for r in rows] == ["1", "2"]
    assert (out / "vary_sigma.png").is_file() and "faults.range_noise_scale = 2" in (out / "summary.md").read_text()
    # an existing folder is kept without --overwrite: one line, exit 2
    again = subprocess.run([*LRFSIM, "study", scen, "-n", "1", "-o", out], capture_output=True, text=True,
                           timeout=120)
    assert again.returncode == 2 and again.stderr.startswith("error: ") and len(again.stderr.splitlines()) == 1


def test_study_help_units_and_defaults() -> None:
    proc = subprocess.run([*LRFSIM, "study", "--help"], capture_output=True, text=True, timeout=60,
                          env={"COLUMNS": "80", "PATH": ""})
    flat = " ".join(proc.stdout.split())
    assert proc.returncode == 0
    assert proc.stdout.splitlines()[0] == "Usage: lrfsim study [OPTIONS] SCENARIO --trials N"
    for words in ("[default: runs/<scenario name>_study]", "[default: 1]", "--dask ADDRESS", "KEY=V1,V2,...",
                  "SI units", "[default: the scenario's seed]"):
        assert words in flat, words


def test_no_wasted_casting(tiny) -> None:
    """A trial that only changes the noise reuses the noise-free cast: the same recording as a full simulation
    for the cast's own seed, new noise for another seed, and the cast itself is left untouched."""
    import numpy as np

    from lrfsim.simulation.simulate import cast_geometry, simulate, simulate_from_geometry

    geometry = cast_geometry(tiny)
    before = geometry.cast.ranges_m.copy()
    full = simulate(tiny)
    reused = simulate_from_geometry(tiny, geometry)
    for name in ("ranges_m", "intensities", "beam_lambda_rad", "scan_stamps_s"):
        assert np.array_equal(getattr(full, name), getattr(reused, name), equal_nan=True), name
    assert np.array_equal(full.tape.distances_m, reused.tape.distances_m)
    other = simulate_from_geometry(tiny.model_copy(update={"seed": tiny.seed + 1}), geometry)
    both = np.isfinite(other.ranges_m) & np.isfinite(full.ranges_m)
    diff = (other.ranges_m - full.ranges_m)[both]
    assert 0.005 < diff.std() < 0.02  # sqrt(2) x the 10 mm range noise
    assert np.array_equal(geometry.cast.ranges_m, before, equal_nan=True)


def test_new_layout_per_trial(tiny) -> None:
    """--new-layout: each trial's V is jittered from its own seed (a new layout, a new cast), so the same seeds give
    other errors than with the scenario's one layout (the design reaches a process pool's workers as one
    TrialDesign: test_perturbed_start_reaches_nominal_yaml_and_pool_gives_the_same_table)."""
    sc = with_field(tiny, "markers.layout.jitter_m", 0.02)
    same = run_trials(sc, 2, seed0=10, recast=True)  # the seeds of this module's other trials of tiny
    new = run_trials(sc, 2, seed0=10, new_layout=True)
    # tiny's one pass crosses each marker with few scan lines: a trial is calibrated, or refused with exit 3 where
    # the markers alone cannot tell a wrong match from a moved marker (lrfcal.stages.markers)
    assert all(r.status == "calibrated" or (r.exit_code == 3 and r.reason) for r in same + new)
    assert any(r.status == "calibrated" for r in same + new), [r.reason for r in same + new]
    for a, b in zip(same, new, strict=True):  # the same seed, another layout: another trial (errors or reason)
        assert a.seed == b.seed and a.csv_row()[2:] != b.csv_row()[2:]


def _nominal(sc) -> dict[str, float]:
    return {**sc.rig.nominal_dh.model_dump(), **sc.rig.nominal_mount.model_dump()}


def test_perturbed_start_draws(tiny) -> None:
    """Each nominal value moves by a uniform draw within +-scale x its half-width, from the seed alone; the truth
    and everything else stay; scale 0 is the scenario itself; a bad scale is refused."""
    import numpy as np

    assert perturbed_start(tiny, 5, 0.0) is tiny
    base = _nominal(tiny)
    steps = []
    for seed in range(40):
        p = perturbed_start(tiny, seed, 2.0)
        assert p.rig.dh == tiny.rig.dh and p.rig.mount == tiny.rig.mount and p.seed == tiny.seed
        assert p.scene == tiny.scene and p.markers == tiny.markers
        moved = _nominal(p)
        steps.append([(moved[k] - base[k]) / (2.0 * h) for k, h in PERTURB_HALF_WIDTH.items()])
    steps_a = np.array(steps)
    assert np.all(np.abs(steps_a) <= 1.0 + 1e-12)
    assert np.all(steps_a.max(0) > 0.5) and np.all(steps_a.min(0) < -0.5)  # spread over the whole width
    assert _nominal(perturbed_start(tiny, 7, 1.0)) == _nominal(perturbed_start(tiny, 7, 1.0))
    assert _nominal(perturbed_start(tiny, 7, 1.0)) != _nominal(perturbed_start(tiny, 8, 1.0))
    for bad in (-1.0, math.nan):
        with pytest.raises(InputError, match="perturb-start"):
            perturbed_start(tiny, 0, bad)


def test_perturbed_start_reaches_nominal_yaml_and_pool_gives_the_same_table(tiny, monkeypatch) -> None:
    """The trial's nominal.yaml (what the calibration reads) holds the perturbed start of that trial's seed, and a
    process pool gives the same table as one process."""
    import lrfsim.trials.trial

    seen: dict[str, dict[str, float]] = {}
    calibrate = lrfsim.trials.trial.calibrate_recording

    def spy(folder, *args, **kwargs):
        data = yaml.safe_load((Path(folder) / "nominal.yaml").read_text())
        seen[folder.name] = {**data["dh"], **data["mount"]}
        return calibrate(folder, *args, **kwargs)

    monkeypatch.setattr(lrfsim.trials.trial, "calibrate_recording", spy)
    serial = run_trials(tiny, 2, seed0=10, workers=1, perturb_start=1.0)
    for trial, seed in ((0, 10), (1, 11)):
        expected = _nominal(perturbed_start(tiny, seed, 1.0))
        assert seen[f"trial_{trial}"] == pytest.approx(expected, abs=1e-12)
        assert seen[f"trial_{trial}"] != pytest.approx(_nominal(tiny), abs=1e-6)
    assert all(r.status == "calibrated" for r in serial), [r.reason for r in serial]
    monkeypatch.undo()
    pooled = run_trials(tiny, 2, seed0=10, workers=2, perturb_start=1.0)
    assert [r.csv_row() for r in pooled] == [r.csv_row() for r in serial]


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    pytest.param("tunnel_v", marks=pytest.mark.xfail(strict=True, reason=(
        "beta's sigma is conservative on tunnel_v since the marker map's uncertainty and the per-marker widening "
        "joined it: over these 30 trials cast anew beta's Monte-Carlo std / predicted is 0.82 and its RMS z 0.76 "
        "(a 0.86 / 0.80, alpha 1.09 / 1.07, b 1.04 / 0.95; measured 2026-12-03, the joint states dequantised; over "
        "100 new layouts every parameter is inside: docs/study.md)"))),
    pytest.param("plane_30deg", marks=pytest.mark.xfail(strict=True, reason=(
        "a's predicted sigma is conservative on plane_30deg: Monte-Carlo std / predicted 0.60 over these 30 trials "
        "cast anew (beta 0.61, RMS z a 0.60, beta 0.60; measured 2026-12-03), 0.83 over 100 with one cast and "
        "0.87 / 0.90 over 100 new layouts (docs/study.md): one board layout freezes where the beams fall on its "
        "markers, whose error the sigma covers over layouts"))),
])
def test_statistical_efficiency(name: str) -> None:
    """The whole method's efficiency on the shipped scenarios, N = 30 trials (seeds 100..129; a local pool of 2):
    for every DH parameter the plan's predicted sigma is within +-25 % of the Monte-Carlo std, and the RMS of
    error / reported sigma is in 0.8-1.25. Every trial is cast anew (``recast``: a new laser phase), because where
    the beams fall on the 5 mm markers is part of a recording's error, which the sigma covers; a study that reuses
    one cast freezes that part into a bias and measures the noise alone (docs/study.md). With N = 30 the std is
    known to about +-13 % and a bias to 1 / sqrt(30) = 0.18 std, so the bias is held to 0.3 std plus two of its
    standard errors (the 0.3 itself is measured with N = 100 by benchmarks/bench_study.py --recast)."""
    from lrfsim.scenario.file import load_scenario

    s = study(load_scenario(ROOT / "scenarios" / f"{name}.yaml"), 30, seed0=100, workers=2, recast=True)
    part = s.parts[0]
    assert all(r.status == "calibrated" for r in part.rows), [r.reason for r in part.rows if r.reason]
    st = part.stats()
    for p in DH_NAMES:
        d = st[p]
        assert 0.75 <= d["std_over_predicted"] <= 1.25, (p, d)
        assert 0.8 <= d["rms_z"] <= 1.25, (p, d)
        assert abs(d["bias"]) < (0.3 + 2 / math.sqrt(30)) * d["std"], (p, d)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason=(
    "measured, 30 trials cast anew (seeds 200..229): RMS z a 1.256, alpha 1.015, b 1.106, beta 1.302: with the noise "
    "correlated along the scan a's and beta's reported sigma are 26-30 % optimistic (1.09 / 1.09 with one cast "
    "reused); the per-scan sandwich does not cover all of it (docs/study.md)"))
def test_reported_sigma_honest_with_range_noise_correlated_along_the_scan() -> None:
    """With the range noise correlated along the scan as a real URG-04LX's (rho = 0.7 between neighbouring beams,
    docs/real-data.md), the reported sigma (the cluster-robust covariance per scan) stays honest: RMS of error /
    reported sigma in 0.8-1.25 for every DH parameter over 30 trials cast anew (measured 0.84-1.09 with one cast,
    docs/study.md). The plan's prediction with the correlation modelled
    (lrfcal.estimate.information.correlation_error_at)
    against the Monte Carlo's scatter is measured in docs/study.md's table, not asserted here."""
    from lrfsim.scenario.file import load_scenario

    sc = load_scenario(ROOT / "scenarios" / "tunnel_v.yaml")
    sc = sc.model_copy(update={"sensor": sc.sensor.model_copy(update={"noise_correlation": 0.7})})
    part = study(sc, 30, seed0=200, workers=2, recast=True).parts[0]
    assert all(r.status == "calibrated" for r in part.rows), [r.reason for r in part.rows if r.reason]
    st = part.stats()
    for p in DH_NAMES:
        assert 0.8 <= st[p]["rms_z"] <= 1.25, (p, st[p])
