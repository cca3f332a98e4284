"""The README's real-rig walkthrough on both shared URG-04LX recordings, through the INSTALLED console scripts:

    lrfcal inspect BAG -o rig.yaml
    lrfcal calibrate BAG --nominal rig.yaml --targetless -o OUT

The outcome must be trustworthy (issue 46, case 3): exit 0 with every estimated DH parameter within its sigma of
the other starts' result (the check "starts agree", lrfcal.stages.starts) and within 4 sigma of the calibration started
from the authors' nominal (forced: its checks may fail, its estimate is the other start's answer), or a refusal
(exit 3) on one error line naming the check that failed. The recordings are shared beside the project, not part of
it: skipped with the reason when absent. Each bag's commands run once (they take several seconds): the inspect and
the calibration from the authors' nominal are the session's (tests/conftest.py: real_inspected, through the installed
console script, shared with tests/test_inspect_dh.py; urg_from_the_authors_nominal, in this process, shared with
tests/test_targetless.py).
"""

from __future__ import annotations

import math
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import yaml
from conftest import REALBAGS, real_bag
from test_cli_usage import _one_error_line, _run

if TYPE_CHECKING:
    from lrfcal.result import CalibrationResult

BAGS = ("cardboard_box", "room_240")
DH = ("a", "alpha", "b", "beta")
#: the checks a targetless refusal can name first
CHECKS = ("clock offset", "starts agree", "convergence", "mirror image", "planes agree", "observability",
          "reduced chi-square", "second opinion", "held-out planes")
N_SIGMA = 4.0


#: per bag: the inspect, the calibration, the rig file inspect wrote, the calibration's output folder
Runs = dict[str, tuple[subprocess.CompletedProcess, subprocess.CompletedProcess, Path, Path]]


@pytest.fixture(scope="module")
def walkthrough(real_inspected: Callable[[str], tuple[subprocess.CompletedProcess, Path]],
                tmp_path_factory: pytest.TempPathFactory) -> Runs:
    """Per bag: (inspect, calibrate, rig file, output folder), run once; the inspect is the session's
    (tests/conftest.py: real_inspected, shared with tests/test_inspect_dh.py)."""
    out: Runs = {}
    for name in BAGS:
        path = REALBAGS / f"{name}.bag"
        if not path.is_file():
            continue
        inspect, rig = real_inspected(name)
        cal = tmp_path_factory.mktemp(name) / "cal"
        calib = _run("lrfcal", "calibrate", path, "--nominal", rig, "--targetless", "--no-figures", "-o", cal,
                     timeout=900)
        out[name] = (inspect, calib, rig, cal)
    return out


def _estimate(cal: dict) -> dict[str, tuple[float, float]]:
    """name -> (value, sigma) of the estimated DH parameters of a calibration.yaml."""
    return {n: (cal["dh"][n]["value"], cal["dh"][n]["sigma"]) for n in DH if cal["dh"][n]["sigma"] is not None}


def _estimated(result: CalibrationResult) -> dict[str, tuple[float, float]]:
    """name -> (value, sigma) of the DH parameters a result estimates (the held ones have no finite sigma)."""
    sigma = result.solution.sigma[6:10]
    dh = result.solution.params.dh
    return {n: (getattr(dh, n), float(s)) for n, s in zip(DH, sigma, strict=True) if math.isfinite(s)}


@pytest.mark.parametrize("name", BAGS)
def test_inspect_proposes_a_rig_file(walkthrough: Runs, name: str) -> None:
    real_bag(name)
    inspect, _, rig_file, _ = walkthrough[name]
    assert "Traceback" not in inspect.stderr and inspect.returncode == 0, inspect.stderr
    rig = yaml.safe_load(rig_file.read_text())
    assert any(rig["dh"][n] != 0 for n in DH), rig["dh"]  # proposed, not the placeholder
    assert rig_file.read_text().startswith("# dh: proposed from the scene's planes")


@pytest.mark.parametrize("name", BAGS)
def test_calibrate_with_its_rig_file_agrees_with_the_other_starts_or_is_refused(
        walkthrough: Runs, name: str, urg_from_the_authors_nominal: Callable[[str], CalibrationResult]) -> None:
    real_bag(name)
    _, calib, _, out = walkthrough[name]
    print(name, "exit", calib.returncode, calib.stderr.strip()[-600:])
    if calib.returncode == 3:
        line = _one_error_line(calib, code=3)
        first = line.removeprefix("error: ").split(":")[0]
        assert first in CHECKS, line
        if first == "starts agree":
            assert "do not determine" in line and any(n in line.split("do not determine")[1] for n in DH), line
        assert not out.exists(), "a refusal writes nothing"
        return
    assert "Traceback" not in calib.stderr and calib.returncode == 0, calib.stderr
    report = (out / "report.md").read_text()
    row = next(r for r in report.splitlines() if r.startswith("| starts agree |"))
    assert "| passed |" in row and ("converge to the estimate within 1 sigma" in row or "worse" in row), row
    ours = _estimate(yaml.safe_load((out / "calibration.yaml").read_text()))
    assert ours, "a result estimates at least one DH parameter"
    # the other start the user might have used: the authors' nominal (forced: only its estimate is compared); the
    # session's run (tests/conftest.py), read as the rig file inspect wrote reads the bag
    theirs = _estimated(urg_from_the_authors_nominal(name))
    print(name, "ours", ours, "from the authors' nominal", theirs)
    for n, (v, s) in ours.items():
        if n in theirs:
            v2, s2 = theirs[n]
            d = math.remainder(v - v2, 2 * math.pi) if n in ("alpha", "beta") else v - v2
            assert abs(d) <= N_SIGMA * math.hypot(s, s2), (n, v, s, v2, s2)


def test_a_rig_file_a_hair_from_the_proposal_is_refused_naming_a_check(walkthrough: Runs, tmp_path: Path) -> None:
    """The box's rig file as inspect wrote it, its beta 0.05 deg further (a user's rounding): exit 0, or a refusal
    that names a check, never the solver. Measured 2026-12-07: from there the planes' cost runs off (the Huber pass
    to a -3.1 m, then no return meets its plane), and the refusal said "targetless solve: 0 of 69413 plane returns
    count at the estimate ... (need 10 each)"; it now says "convergence: the planes' cost, minimised from the rig
    file's DH (...), ran off ...: the scene's planes do not hold the DH near the rig file's values"."""
    real_bag("cardboard_box")
    _, _, rig_file, _ = walkthrough["cardboard_box"]
    rig = yaml.safe_load(rig_file.read_text())
    rig["dh"]["beta"] = round(rig["dh"]["beta"] + math.radians(0.05), 4)
    moved = tmp_path / "rig.yaml"
    moved.write_text(yaml.safe_dump(rig))
    calib = _run("lrfcal", "calibrate", REALBAGS / "cardboard_box.bag", "--nominal", moved, "--targetless",
                 "--no-figures", "-o", tmp_path / "cal", timeout=900)
    print("exit", calib.returncode, calib.stderr.strip()[-600:])
    if calib.returncode == 0:
        return
    line = _one_error_line(calib, code=3)
    assert line.removeprefix("error: ").split(":")[0] in CHECKS and "targetless solve" not in line, line
    assert not (tmp_path / "cal").exists(), "a refusal writes nothing"
