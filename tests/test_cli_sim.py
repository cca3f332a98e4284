"""The lrfsim CLI: simulate/run write every file; bad input gives exit code 2, one line, and nothing written."""

from __future__ import annotations

import copy
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from lrfcal.io.files import MANIFEST_NAME
from lrfsim.cli import main

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
FILES = sorted([MANIFEST_NAME, "bag", "distances.csv", "ground_truth.yaml", "nominal.yaml", "scenario.yaml"])


def _write_small(tmp_path: Path, **servo: object) -> Path:
    data = copy.deepcopy(yaml.safe_load((SCENARIOS / "tunnel_v.yaml").read_text()))
    data["servo"].update({"start_rad": 0.05, "end_rad": -0.05, "passes": 1, "settle_s": 0.05, **servo})
    path = tmp_path / "small.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def _main(argv: list[str]) -> int:
    try:
        main(argv)
    except SystemExit as e:
        return int(e.code or 0)
    return 0


def test_simulate_writes_all_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scen = _write_small(tmp_path)
    out = tmp_path / "rec"
    assert _main(["simulate", str(scen), "-o", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == FILES
    assert (out / "bag" / "metadata.yaml").is_file()
    assert "scans" in capsys.readouterr().out
    # a second time: refused (exit 2, one line), then replaced with --overwrite
    assert _main(["simulate", str(scen), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "--overwrite" in err[0]
    assert _main(["simulate", str(scen), "-o", str(out), "--overwrite"]) == 0


def test_bad_scenario_exit_2_one_line_nothing_written(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    scen = _write_small(tmp_path, speed_rad_s=-1.0)
    out = tmp_path / "rec"
    assert _main(["simulate", str(scen), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert err[0].startswith("error: ") and str(scen) in err[0] and "servo.speed_rad_s" in err[0]
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.yaml"]
    # a missing file, too
    assert _main(["run", str(tmp_path / "nope.yaml"), "-o", str(out)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not out.exists()


def test_run_closes_the_loop(full_sweep_run: tuple[subprocess.CompletedProcess, Path], tmp_path: Path) -> None:
    """`lrfsim run`: simulate, calibrate, compare; the run folder holds everything; a rerun is replaced. The first
    run is the session's (tests/conftest.py: full_sweep_run, the installed console script on the full sweep at 30
    deg/s, one pass, shared with tests/test_output_names.py); the rerun, in a copy of its folder, is `python -m`."""
    proc, first = full_sweep_run
    assert proc.returncode in (0, 1), proc.stderr  # 1: tolerances missed, still a complete run
    run_dir = first / "runs" / "tunnel_v"
    assert sorted(p.name for p in run_dir.iterdir()) == sorted([MANIFEST_NAME, "calibration", "comparison.md",
                                                                "recording", "rerun.rrd"])
    assert sorted(p.name for p in (run_dir / "recording").iterdir()) == FILES
    for name in ("calibration.yaml", "rig.urdf", "cloud_before.ply", "cloud_after.ply", "report.md"):
        assert (run_dir / "calibration" / name).is_file(), name
    # independent range noise: the marker returns' neighbouring beams show no correlation the covariance would hold
    rho = yaml.safe_load((run_dir / "calibration" / "calibration.yaml").read_text())["range_noise_correlation"]
    assert rho["pairs"] > 0 and rho["rho"] < 0.3 and rho["in_covariance"] is False, rho
    for words in ("Table I", "Table III", "estimate", "paper's method", "width", "plate"):
        assert words in proc.stdout, words
    # one line says the simulated scanner was idealised and where the systematic errors' cost is measured
    sensor = [line for line in proc.stdout.splitlines() if line.startswith("sensor: ")]
    assert len(sensor) == 1 and "idealised" in sensor[0] and sensor[0].endswith("docs/sensor_errors.md"), sensor
    assert "Table I" in (run_dir / "comparison.md").read_text()
    # run again, with --spawn where no viewer can start: the default run folder is replaced, nothing else is left
    # beside it, and one warning line says where the rerun recording went
    work = tmp_path / "again"
    shutil.copytree(first, work)
    run_dir = work / "runs" / "tunnel_v"
    scen = next(work.glob("*.yaml"))
    proc = subprocess.run([sys.executable, "-m", "lrfsim.cli", "run", str(scen), "--spawn"], cwd=work,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode in (0, 1), proc.stderr
    assert sorted(p.name for p in (work / "runs").iterdir()) == ["tunnel_v"]
    assert "Traceback" not in proc.stderr
    warn = proc.stderr.strip().splitlines()
    assert len(warn) == 1 and warn[0].startswith("warning: --spawn: no rerun viewer") and "rerun.rrd" in warn[0]
    assert (run_dir / "rerun.rrd").stat().st_size > 0
    assert "residual RMS" in proc.stdout and "marker returns on" in proc.stdout
    assert "marker returns on" in (run_dir / "calibration" / "report.md").read_text()  # the terminal's wording
    bad = subprocess.run([sys.executable, "-m", "lrfsim.cli", "simulate", "x.yaml", "-o", "o"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and not (tmp_path / "o").exists()
