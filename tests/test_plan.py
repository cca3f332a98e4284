"""lrfsim plan (issue 10): predicted sigma from the Fisher information of the noise-free geometry."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import tiered

from lrfsim.plan.prediction import plan
from lrfsim.plan.text import format_plan
from lrfsim.scenario.file import parse_scenario, with_changes

ROOT = Path(__file__).resolve().parents[1]
LRFSIM = [sys.executable, "-m", "lrfsim.cli"]
NAMES = ("a", "alpha", "b", "beta", "x", "y", "z", "rx", "ry", "rz")


def _data(base: str, **changes: object) -> dict:
    return with_changes(yaml.safe_load((ROOT / "scenarios" / f"{base}.yaml").read_text()), changes)


def _fast_tunnel(**changes: object) -> dict:
    """tunnel_v swept at 30 deg/s, 2 passes (a third of the scans)."""
    return _data("tunnel_v", **{"servo.speed_rad_s": math.radians(30.0), "servo.passes": 2, **changes})


def _write(tmp_path: Path, data: dict, name: str = "s.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(scope="module")
def tunnel_plan():
    return plan(parse_scenario(_fast_tunnel(), "fast tunnel"))


def test_plan_tunnel_finite_and_determined(tunnel_plan) -> None:
    p = tunnel_plan
    assert p.determined and p.clock_estimated
    assert set(NAMES) | {"clock_offset"} == set(p.sigma)
    for n in NAMES:
        assert math.isfinite(p.sigma[n]) and p.sigma[n] > 0, (n, p.sigma[n])
    # sub-millimetre and sub-0.1-degree on the paper's tunnel layout (tolerances there are ~4 sigma)
    assert p.sigma["a"] < 1e-3 and p.sigma["b"] < 1e-3
    assert p.sigma["alpha"] < math.radians(0.1) and p.sigma["beta"] < math.radians(0.1)
    assert p.n_surface_returns > 0 and p.n_markers_seen == p.n_markers == 18


def test_surface_returns_add_information(tunnel_plan) -> None:
    markers = plan(parse_scenario(_fast_tunnel(), "fast tunnel"), surfaces=False)
    assert markers.n_surface_returns == 0
    # the surfaces add data and two unknowns (the range offset and the marker range bias the calibration
    # estimates with them): the DH parameters gain, the mount may lose a little to those two
    for n in ("a", "alpha", "b", "beta"):
        assert tunnel_plan.sigma[n] <= markers.sigma[n] * 1.05, n
    assert tunnel_plan.sigma["b"] < 0.8 * markers.sigma["b"]


def test_one_way_sweep_holds_the_clock() -> None:
    p = plan(parse_scenario(_fast_tunnel(**{"servo.passes": 1}), "one way"), surfaces=False)
    assert "clock_offset" not in p.sigma and not p.clock_estimated
    assert any("one-way" in n for n in p.notes)


def test_more_noise_more_sigma(tunnel_plan) -> None:
    assert tunnel_plan.range_sigma_m == pytest.approx(0.010)  # the UTM-30LX-EW below 10 m, as the calibration
    noisy = plan(parse_scenario(_fast_tunnel(), "fast tunnel"), range_sigma_m=0.03)
    assert noisy.sigma["a"] > 1.5 * tunnel_plan.sigma["a"]
    scaled = plan(parse_scenario(_fast_tunnel(**{"faults.range_noise_scale": 2.0}), "noisy"), surfaces=False)
    assert scaled.range_sigma_m == pytest.approx(0.020)  # the scenario's own sensor noise


def test_plan_json_cli(tmp_path: Path) -> None:
    proc = subprocess.run([*LRFSIM, "plan", _write(tmp_path, _fast_tunnel()), "--json"], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert {"sigma", "weakest", "determined", "tolerances_reachable"} <= set(out)
    assert set(NAMES) <= set(out["sigma"]) and all(out["sigma"][n] > 0 for n in NAMES)
    assert out["determined"] is True and isinstance(out["tolerances_reachable"], bool)


def test_board_across_the_axis_is_flagged(tmp_path: Path) -> None:
    """All markers at one axial distance: alpha and b are one valley (plane_0deg.yaml's comment)."""
    data = _data("plane_0deg", **{"scene.board.pose": {"x": 1.0, "y": 0.0, "z": 1.0, "roll": 0.0,
                                                       "pitch": -math.pi / 2, "yaw": 0.0},
                                  "servo.speed_rad_s": math.radians(30.0)})
    proc = subprocess.run([*LRFSIM, "plan", _write(tmp_path, data)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3, proc.stderr
    assert "NOT DETERMINED" in proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "not determined" in lines[0]
    assert "along the motor axis" in lines[0]


def test_plan_help_units_and_defaults() -> None:
    proc = subprocess.run([*LRFSIM, "plan", "--help"], capture_output=True, text=True, timeout=60,
                          env={"COLUMNS": "80", "PATH": ""})
    flat = " ".join(proc.stdout.split())
    assert proc.returncode == 0
    assert "[m]" in flat and "[default: the scenario's sensor noise" in flat and "--json" in flat
    assert proc.stdout.splitlines()[0].startswith("Usage: lrfsim plan [OPTIONS] SCENARIO")


def test_plan_predicts_the_sigma_a_precise_scanner_reports(recording_of) -> None:  # type: ignore[no-untyped-def]
    """A scanner with 2 mm range noise (the fast tunnel): the model's own errors (the footprint on the markers and
    walls, the joint states' interpolation) are then a large part of the sigma of b (0.021 mm beside 0.030 mm of
    noise; before the joint states' quantisation was taken out, lrfcal.model.motor.dequantised, they were most of
    it), and the calibration reports them (its per-scan widening). plan adds the same model-error part
    (lrfcal.estimate.information.model_error_at) and predicts the reported sigma within 25 % for every DH parameter.
    (Measured: reported / plan 1.08-1.19; on seeds 1 and 2 before the dequantisation 0.97-1.20.)"""
    from lrfsim.trials.trial import calibrate_recording

    sc = parse_scenario(_fast_tunnel(**{"sensor.noise_bands": [{"up_to_m": 60.0, "sigma_m": 0.002}]}), "precise")
    p = plan(sc)
    statistical_b = math.sqrt(p.sigma["b"] ** 2 - p.model_sigma["b"] ** 2)
    assert p.model_sigma["b"] > 0.5 * statistical_b, (p.model_sigma["b"], statistical_b)
    t = calibrate_recording(recording_of(sc))
    assert t.status == "calibrated", t.describe()
    for i, n in enumerate(("a", "alpha", "b", "beta")):
        assert 0.75 <= t.sigma[i] / p.sigma[n] <= 1.25, (n, t.sigma[i], p.sigma[n], p.model_sigma[n])
    assert "model_error_sigma" in p.to_json() and "model-error part" in format_plan(p)


@pytest.mark.parametrize("which", tiered(["fast tunnel", "tilted broad truth"]))
def test_sparse_cast_has_every_marker_return(which: str) -> None:
    """plan casts only the scans that can see a marker and every SURFACE_SCAN_STEP-th other one: the marker
    returns are those of the full cast, bit for bit, from fewer scans (here; on 2 of 46 scenarios checked the
    detection's background, estimated from the scans cast, moved 0.3-0.7 % of them at the blobs' edges); joined
    with the rest it is the full cast;
    the predicted sigmas move by what another sample of the surface returns moves them (a few %)."""
    import numpy as np

    from lrfsim.plan.prediction import marker_observations, sparse_geometry
    from lrfsim.simulation.simulate import cast_geometry
    from lrfsim.testing.random_scenarios import random_scenario_wide

    sc = (parse_scenario(_fast_tunnel(), "fast tunnel") if which == "fast tunnel"
          else random_scenario_wide(12, alpha_kind="tilted"))
    full = cast_geometry(sc, noise=False)
    sparse = sparse_geometry(sc)
    cast = np.isfinite(sparse.cast.ranges_m).any(axis=1)
    assert cast.mean() < (0.5 if which == "fast tunnel" else 1.0), cast.mean()  # a tilted plane sees markers longer
    a, b = marker_observations(sc, full)[0], marker_observations(sc, sparse)[0]
    assert len(a) > 20
    for f in ("scan", "beam", "marker", "ranges_m", "intensity", "lambda_rad"):
        assert np.array_equal(getattr(a, f), getattr(b, f)), f
    both = sparse_geometry(sc, rest_of=sparse).cast.ranges_m
    assert np.array_equal(np.isnan(both), np.isnan(full.cast.ranges_m))
    assert np.nanmax(np.abs(both - full.cast.ranges_m)) < 1e-3
    if which != "fast tunnel":
        return
    p_sparse, p_full = plan(sc), plan(sc, geometry=full)
    for n in ("a", "alpha", "b", "beta"):
        assert abs(p_sparse.sigma[n] / p_full.sigma[n] - 1) < 0.1, (n, p_sparse.sigma[n], p_full.sigma[n])


def test_plan_holds_the_model_error_of_turning_crossings(tunnel_plan, monkeypatch: pytest.MonkeyPatch) -> None:
    """Where the sweep turns on a marker the calibration widens the DH covariance by the difference the in-plane
    variant makes (lrfcal.stages.markers.MarkerWay.systematics); plan predicts that term from the noise-free returns
    (lrfcal.estimate.information.turning_error_at): broad truth 28, a tilted spin whose turning crossings bias alpha by
    about 0.07 deg, gets a wider alpha than the statistics alone give, and says why. tunnel_v has no such crossing."""
    import numpy as np

    import lrfsim.plan.prediction as plan_module
    from lrfsim.testing.random_scenarios import random_scenario_wide

    assert not any("turn on some markers" in n for n in tunnel_plan.notes)
    sc = random_scenario_wide(28, broad=True)
    with_term = plan(sc)
    assert any("turn on some markers" in n for n in with_term.notes), with_term.notes
    monkeypatch.setattr(plan_module, "turning_error_at", lambda *a, **k: np.zeros((4, 4)))
    without = plan(sc)
    assert with_term.sigma["alpha"] > 2.0 * without.sigma["alpha"], (with_term.sigma, without.sigma)
    assert math.radians(0.04) < with_term.sigma["alpha"] < math.radians(0.15)
    for n in ("x", "y", "z", "rx", "ry", "rz"):
        assert with_term.sigma[n] == pytest.approx(without.sigma[n], rel=1e-12), n


def test_plan_counts_the_marker_returns_the_detection_sees() -> None:
    """plan's marker returns are the calibration's detections, each owned by the marker its true ray passes. Broad
    truth 5's marker 1 sits 0.36 m from the scanner, where it and the wall behind it both saturate: a brightness
    bound (3x the brightest surface at that range, above saturation there) kept only its edge beams, a one-sided
    sample 12.8 standard errors off its centre; the detection, whose contrast against the wall is 7x there, below
    its 10x floor, sees none of it, and neither does plan now."""
    from lrfsim.plan.prediction import marker_observations, sparse_geometry
    from lrfsim.simulation.faults import detected_mask, marker_returns
    from lrfsim.testing.random_scenarios import random_scenario_wide

    sc = random_scenario_wide(5, broad=True)
    obs, _, _, _, _, result = marker_observations(sc, sparse_geometry(sc))
    assert len(obs) > 1000
    assert detected_mask(result, sc)[obs.scan, obs.beam].all()
    by_brightness = marker_returns(result, sc)
    assert (by_brightness == 1).any() and not (obs.marker == 1).any()


def test_plan_predicts_the_smallest_scale_error_the_calibration_finds(shipped_recording) -> None:  # type: ignore[no-untyped-def]
    """plan's 1-sigma of each intrinsic the calibration holds and tests (the gear ratio, the range scale, the incidence
    bias) is the sigma of the calibration's own score test on the recording, within 25 % (measured: 0.88 and 0.89 on
    tunnel_v; plane_30deg 0.99 and 0.91): a researcher learns which error the layout would find before building it."""
    from lrfcal.pipeline import CalibConfig
    from lrfcal.stages.joint import SCALES
    from lrfsim.scenario.file import load_scenario
    from lrfsim.trials.trial import calibrate_recording

    p = plan(load_scenario(ROOT / "scenarios" / "tunnel_v.yaml"))
    t = calibrate_recording(shipped_recording("tunnel_v"), CalibConfig(baseline=False, geometry=False),
                            keep_result=True)
    assert t.result is not None
    for n in SCALES:
        value, sigma = t.result.solution.held_score[n]
        assert 0.75 <= sigma / p.scale_sigma[n] <= 1.25, (n, sigma, p.scale_sigma[n])
    assert set(p.to_json()["held_scale_sigma"]) == set(SCALES) and "intrinsics held and tested" in format_plan(p)


def test_plan_models_range_noise_correlated_along_the_scan(tunnel_plan) -> None:
    """sensor.noise_correlation 0.7 (a real URG's, docs/real-data.md): plan adds the sandwich term of the AR(1)
    noise (lrfcal.estimate.information.correlation_error_at): the DH sigmas about double, as the Monte Carlo's scatter
    does
    (docs/study.md, "Range noise correlated along the scan"), and the plan says which noise it assumed."""
    p = plan(parse_scenario(_fast_tunnel(**{"sensor.noise_correlation": 0.7}), "fast tunnel, rho 0.7"))
    assert p.range_correlation == 0.7 and tunnel_plan.range_correlation == 0.0
    for n in ("a", "alpha", "b", "beta"):
        assert 1.6 < p.sigma[n] / tunnel_plan.sigma[n] < 2.6, (n, p.sigma[n], tunnel_plan.sigma[n])
    assert "correlated 0.7 between neighbouring beams" in format_plan(p)
    assert p.to_json()["range_noise_correlation"] == 0.7
